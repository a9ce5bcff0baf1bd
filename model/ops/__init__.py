"""Kernels behind one dispatch module each (scan.py, sparse_conv.py), their plain-torch twins (*_torch.py)
and Triton fast paths (*_triton.py, CUDA only); every fast path is tested against its twin."""
