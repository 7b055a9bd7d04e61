"""Training algorithms: one sub-package per algorithm."""
