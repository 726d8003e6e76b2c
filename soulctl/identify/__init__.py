"""Identification of the plant from closed-loop telemetry (`soulctl telemetry identify`):
the loop delay, the optical gains, the measurement noise, the Tip/Tilt vibration lines and
the turbulence, each with its uncertainty, written as a plant file (``plant``) that
`filter design|analyze --plant`, `loop run --plant` and `rtc check --plant` take."""
