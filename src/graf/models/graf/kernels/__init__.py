"""GRaF's fast inference on a CPU: a compiled fused-attention kernel (:mod:`.native`, built at first use) and the
Transformer blocks in a feature-major layout that feeds it (:mod:`.blocks`)."""
