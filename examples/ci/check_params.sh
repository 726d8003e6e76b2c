#!/bin/sh
# From a night's telemetry to a gain file checked before it goes to the RTC: the job a CI
# pipeline runs (exit 0: safe to upload; 3: a mode is unstable or below a margin, do not
# upload; 2: bad input; 1: a bug).
#
#   examples/ci/check_params.sh TELEMETRY CONFIG [OUTDIR]
#
# TELEMETRY: the night's record (soulctl .h5, AOT .fits or an LBT Data_<TN> folder).
# CONFIG:    the system's run description (TOML; modes, frame rate and filters of the record).
set -eu
telemetry=$1
config=$2
out=${3:-ci-out}
mkdir -p "$out"

# 1. the plant of the night: delay, optical gains, noise, vibrations, seeing
soulctl telemetry identify "$telemetry" --out "$out/plant.toml" --json > "$out/identify.json"
# 2. a Tip/Tilt IIR filter for that night's vibrations and noise (next to the one in use)
soulctl filter design --plant "$out/plant.toml" --out "$out/roots.csv" --json > "$out/design.json"
# 3. the gains MGM would apply after the record (offline, on the telemetry itself)
soulctl optimize gains --method mgm --telemetry "$telemetry" --config "$config" \
    --delay-frames "$(python3 -c "import tomllib,sys; print(tomllib.load(open(sys.argv[1],'rb'))['delay']['frames'])" "$out/plant.toml")" \
    --out "$out/gains.toml" --json > "$out/gains.json"
# 4. the check: every mode stable with margins on the identified plant; exit 3 fails the job
status=0
soulctl rtc check "$out/gains.toml" --config "$config" --plant "$out/plant.toml" --json > "$out/check.json" || status=$?
if [ "$status" -eq 3 ]; then
    echo "rtc check: the gains are not safe to upload (see $out/check.json)" >&2
fi
exit "$status"
