"""GRaF: geometry-aware RF radiance field with neural ray tracing (see :mod:`.module`)."""

from graf.models.graf.attention import CrossAttentionBlock, SelfAttentionBlock
from graf.models.graf.encoder import ResNetEncoder
from graf.models.graf.encoding import PositionalEncoding, normalize_offsets, normalize_positions
from graf.models.graf.module import GRaFModule
from graf.models.graf.rays import num_samples, sample_voxels

__all__ = ["GRaFModule", "ResNetEncoder", "PositionalEncoding", "normalize_positions", "normalize_offsets",
           "CrossAttentionBlock", "SelfAttentionBlock", "num_samples", "sample_voxels"]
