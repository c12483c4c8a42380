"""State estimation: a model's state set from a measured window of u and y."""
