"""Evaluation of trained policies: per-episode metrics and their aggregation."""

from coin_app.evaluation.metrics import (
    METRIC_KEYS,
    OUTCOMES,
    EpisodeRecorder,
    VehicleRecord,
    aggregate,
    episode_metrics,
    metrics_from_infos,
)

__all__ = ["METRIC_KEYS", "OUTCOMES", "EpisodeRecorder", "VehicleRecord", "aggregate", "episode_metrics", "metrics_from_infos"]
