"""Training: the in-process trainer, the learner, checkpoints, metrics, offline training, export."""
