"""The feature cache: a Zarr v3 group per cache key, with a provenance manifest, under a root that is a
local folder or an object-store URL (s3://, gs://, az://).

    <cache_root>/<key>/                    Zarr v3 group (copy the folder, or push/pull it, to share the cache)
      features/<camera>/<HxW>              [frames, H*W, C] stored dtype (fp16 default)
      features/<camera>/<extra>            extra token arrays of native towers, e.g. "connector"
      index/{index,episode_index,frame_index,task_index,suite_index}
      lowdim/{timestamp,state,action}
      _progress/block-NNNNNN.json          per-block checksums while writing (removed once complete)
      attrs: manifest, layout, initialized, complete, checksums
    <cache_root>/<key>.lock               local roots: advisory lock held by the writing process
    <cache_root>/<key>.lease/NNNNNNNN     object stores: the writer lease (graftcache.store.lease)
"""

from graftcache.store.cache import BrokenCache, FeatureCache, list_caches, scan_caches
from graftcache.store.key import IdentityDifference, cache_key, compare_identity, identity_of
from graftcache.store.manifest import FORMAT_VERSION, DatasetRecord, Manifest
from graftcache.store.roots import Root, cache_root, open_root

__all__ = ["FORMAT_VERSION", "BrokenCache", "DatasetRecord", "FeatureCache", "IdentityDifference", "Manifest", "Root",
           "cache_key", "cache_root", "compare_identity", "identity_of", "list_caches", "open_root", "scan_caches"]
