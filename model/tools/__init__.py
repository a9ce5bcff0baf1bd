"""Tools around the network: benchmarks, op counting, model info, and the model commands."""
