"""Training, evaluation, checkpoints and runs."""
