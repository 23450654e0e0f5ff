"""Plain data, no torch modules: references, recordings."""
