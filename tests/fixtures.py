"""Shared test fixtures (imported by test modules as ``from fixtures import ...``, as ``device_audit``)."""

# Fast cars without brakes or rolling resistance (the bicycle model): under random actions they crash and
# leave the road within a few steps, so short test episodes see respawns, time-outs and terminations.
NO_BRAKES = {
    "model": "bicycle",
    "brake_linear": 0.0,
    "brake_sat_intercept": 0.0,
    "brake_sat_slope": 0.0,
    "coast_decel": 0.0,
    "throttle_accel": 8.0,
}
