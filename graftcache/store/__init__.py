"""The feature cache: a Zarr v3 group per cache key, with a provenance manifest.

    <cache_root>/<key>/                    Zarr v3 group (copy the folder to share the cache)
      features/<camera>/<HxW>              [frames, H*W, C] stored dtype (fp16 default)
      features/<camera>/<extra>            extra token arrays of native towers, e.g. "connector"
      index/{index,episode_index,frame_index,task_index,suite_index}
      lowdim/{timestamp,state,action}
      attrs: manifest, layout, initialized, complete, checksums
    <cache_root>/<key>.lock               advisory lock held by the writing process
"""

from graftcache.store.cache import FeatureCache, cache_root, list_caches
from graftcache.store.key import FORMAT_VERSION, IdentityDifference, cache_key, compare_identity, identity_of

__all__ = ["FORMAT_VERSION", "FeatureCache", "IdentityDifference", "cache_key", "cache_root", "compare_identity",
           "identity_of", "list_caches"]
