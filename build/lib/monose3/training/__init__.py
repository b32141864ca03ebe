"""Training: samples (from DREAM folders or synthesised on the device), the loop, checkpoints
and weight shards. Importing the package loads nothing heavy (see :mod:`monose3.training.formats`)."""
