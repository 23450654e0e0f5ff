"""TorchRL environments: the tracking environment and its observation layout."""
