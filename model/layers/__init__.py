"""The network's layers: voxelizer, sparse convs, Mamba, PHiM block, polar-to-BEV, BEV backbone, head."""
