"""RF Gaussian splatting: a per-scene method of deformable 2-D Gaussians on the spectrum grid, SwiftWRF's form,
rendered by a separable rasterizer in torch (see :mod:`.module`)."""

from graf.models.rf_gs.gaussians import GaussianField, split_plan, split_rows
from graf.models.rf_gs.module import RFGSModule
from graf.models.rf_gs.rasterizer import render, render_dense, wrapped_distance

__all__ = ["RFGSModule", "GaussianField", "render", "render_dense", "split_plan", "split_rows", "wrapped_distance"]
