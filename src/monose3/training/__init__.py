"""Training: samples (from DREAM folders or synthesised on the device), the loop, weight shards.

Importing the package itself loads nothing heavy: the torch-free checks read ``SHARD_INDEX``.
"""

SHARD_INDEX = "weights.json"  # the index file of a shard set (monose3.training.shards)
