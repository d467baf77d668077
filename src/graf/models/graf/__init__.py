"""GRaF: geometry-aware RF radiance field with neural ray tracing (see :mod:`.module`)."""

from graf.models.graf.attention import CrossAttentionBlock, SelfAttentionBlock
from graf.models.graf.encoder import ResNetEncoder
from graf.models.graf.module import GRaFModule

__all__ = ["GRaFModule", "ResNetEncoder", "CrossAttentionBlock", "SelfAttentionBlock"]
