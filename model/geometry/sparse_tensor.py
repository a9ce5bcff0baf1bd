"""The sparse 3D tensor passed between the voxelizer, the PHiM blocks and the BEV mapping.

Coordinates are polar voxel indices. Column order is fixed: (batch, r, theta, z). A batch item is one
sector; sectors never mix inside convolutions or the local Mamba (the paper trains that way, to stay causal).
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

BATCH, R, THETA, Z = 0, 1, 2, 3  # columns of SparseTensor.coords
SENTINEL: int = 2**62  # the linear key of a padding row (fixed-capacity sites): sorts after every real key


@dataclass(frozen=True)
class SparseTensor:
    features: Tensor  # (N, C) float
    coords: Tensor  # (N, 4) int64: batch, r, theta, z
    spatial_shape: tuple[int, int, int]  # (R, THETA, Z) extent of the grid at this resolution
    batch_size: int

    def __post_init__(self) -> None:
        if self.features.shape[0] != self.coords.shape[0]:
            raise ValueError(
                f"features {tuple(self.features.shape)} and coords {tuple(self.coords.shape)} differ in N"
            )

    def replace(self, features: Tensor) -> SparseTensor:
        """Same sites, new features (N, C')."""
        return SparseTensor(features, self.coords, self.spatial_shape, self.batch_size)

    @property
    def num_sites(self) -> int:
        return int(self.coords.shape[0])


def linear_key(coords: Tensor, spatial_shape: tuple[int, int, int]) -> Tensor:
    """(N, 4) coords -> (N,) int64 keys ordered lexicographically by (batch, theta, r, z).

    This is the paper's serialization order: azimuth first, then radius, then height.
    """
    n_r, n_t, n_z = spatial_shape
    b, r, t, z = coords.unbind(1)
    return ((b * n_t + t) * n_r + r) * n_z + z


def to_dense(x: SparseTensor) -> Tensor:
    """Dense (B, C, R, THETA, Z) copy, for tests on small grids only."""
    n_r, n_t, n_z = x.spatial_shape
    out = x.features.new_zeros(x.batch_size, x.features.shape[1], n_r, n_t, n_z)
    b, r, t, z = x.coords.unbind(1)
    out[b, :, r, t, z] = x.features
    return out
