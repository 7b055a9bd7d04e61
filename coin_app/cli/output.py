"""What the commands print: the six COIN metrics and the vehicle counts as aligned rows."""

from __future__ import annotations

import math

from coin_app.evaluation.metrics import METRIC_KEYS

CONSOLE_FORMATS = {"efficiency": "{:.0f}", "safety": "{:.0f}", "avg_travel_steps": "{:.1f}"}  # the rates: "{:.3f}"
# (key, label, format) of the six COIN metrics as the commands print them
METRIC_ROWS = tuple((k, k.replace("_", " ").replace("out of road", "off-road"), CONSOLE_FORMATS.get(k, "{:.3f}")) for k in METRIC_KEYS)
# ... then the arrivals-only travel steps and the vehicle counts ("count": an integer, or one decimal for a mean)
CONSOLE_ROWS = (
    *METRIC_ROWS,
    ("avg_travel_steps_arrived", "travel (arrived)", "{:.1f}"),
    ("num_vehicles", "vehicles", "count"),
    ("num_timeout", "time-outs", "count"),
)


def shown(value: float, fmt: str) -> str:
    """``value`` as the console shows it: ``fmt`` (``"count"``: no decimals if whole, else one); ``n/a`` for NaN."""
    if isinstance(value, float) and math.isnan(value):
        return "n/a"
    if fmt == "count":
        return f"{value:.0f}" if float(value).is_integer() else f"{value:.1f}"
    return fmt.format(value)


def format_metrics(metrics: dict[str, float]) -> str:
    """The six COIN metrics, the arrivals' travel steps, vehicles and time-outs as an aligned two-column table."""
    return "\n".join(f"  {label:<18}{shown(metrics.get(key, math.nan), fmt):>10}" for key, label, fmt in CONSOLE_ROWS)
