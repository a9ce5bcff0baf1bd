"""The fixed-shape streaming step ("graph engine"): every tensor of a step has a shape fixed by its bucket
(streams, points, voxels, coarse sites), so the step runs with no host synchronisation between the input
copy and the candidate copy, compiles with torch.compile(fullgraph=True) and replays as a CUDA graph.
The eager modules (`model.layers`, `model.stream`) are its reference twin; both use the same weights."""
