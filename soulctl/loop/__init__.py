"""The simulated closed loop: delay line, one explicit step per frame, metrics."""
