"""Vision encoders as registry entries: name -> EncoderSpec -> Encoder (preprocess + patch grid).

Importing this package registers the built-in entries (catalog.py) and the `timm:` / `hf:`
families; other packages add theirs with `register_encoder(spec, builder)`.
"""

from graftcache.encoders import catalog as _catalog  # noqa: F401  (registers the built-in entries)
from graftcache.encoders.encoder import Encoder
from graftcache.encoders.registry import get_spec, list_encoders, load_encoder, register_encoder, register_family
from graftcache.encoders.spec import Builder, EncoderSpec, LoadRequest, weights_info

# Native towers (smolvla-native, pi05-native) live with their backbones and register themselves; imported
# last because they build on the names above.
from graftcache.backbones import native as _native  # noqa: E402,F401  (registers the native towers)

__all__ = ["Builder", "Encoder", "EncoderSpec", "LoadRequest", "get_spec", "list_encoders", "load_encoder",
           "register_encoder", "register_family", "weights_info"]
