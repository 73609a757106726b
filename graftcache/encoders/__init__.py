"""Vision encoders as registry entries: name -> EncoderSpec -> Encoder (preprocess + patch grid).

Importing this package registers the built-in entries (catalog.py: named encoders, the backbones' native
towers, built lazily by graftcache.backbones.tower_encoder) and the `timm:` / `hf:` families; other packages add
theirs with `register_encoder(spec, builder)`.
"""

from graftcache.encoders import catalog as _catalog  # noqa: F401  (registers the built-in entries)
from graftcache.encoders.encoder import Encoder
from graftcache.encoders.registry import (
    Builder,
    get_spec,
    list_encoders,
    load_encoder,
    register_encoder,
    register_family,
)
from graftcache.encoders.spec import EncoderSpec, LoadRequest, weights_info

__all__ = ["Builder", "Encoder", "EncoderSpec", "LoadRequest", "get_spec", "list_encoders", "load_encoder",
           "register_encoder", "register_family", "weights_info"]
