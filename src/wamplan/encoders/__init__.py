"""Frozen image encoders behind a registry: DINOv3 / DINOv2 (transformers) and the CPU default
``patch-pixels``. See ``base.py`` for the interface.

    from wamplan.encoders import make_encoder
    enc = make_encoder("dinov3-vitl16", path="/models/dinov3-vitl16")   # 224 px -> (B, 196, 1024)
    enc = make_encoder("patch-pixels")                                   # no weights, CPU
"""

from wamplan.encoders.base import (ENCODERS, IMAGENET_MEAN, IMAGENET_STD, FrozenEncoder, encoder_names,
                                   make_encoder, register_encoder)
from wamplan.encoders.hf import DINOV2_ENV, DINOV3_ENV, HF_ENCODERS, HFViTEncoder, load_hf_model
from wamplan.encoders.patch_pixels import PatchPixelEncoder, dct_projection, orthogonal_projection

__all__ = ["ENCODERS", "HF_ENCODERS", "DINOV2_ENV", "DINOV3_ENV", "IMAGENET_MEAN", "IMAGENET_STD",
           "FrozenEncoder", "HFViTEncoder", "PatchPixelEncoder", "encoder_names", "load_hf_model",
           "make_encoder", "dct_projection", "orthogonal_projection", "register_encoder"]
