"""Training: samples (from DREAM folders or synthesised on the device), the loop, weight shards."""
