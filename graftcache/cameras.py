"""Which cache camera feeds which camera slot of a policy: by name, or by a map the user gives, never by position.

A policy names its image inputs (`observation.images.<name>`), a cache the dataset cameras it holds. LIBERO's
own releases disagree (the wrist camera is `image2` in some, `wrist_image` in others; lerobot 0.6 datasets may
say `agentview` / `eye_in_hand`), so pairing by position would be a guess that silently feeds the wrist view
into the third-person slot. When the names differ, the user says which camera feeds which slot (`--camera-map
POLICY=CACHE[,...]`, a recipe's `camera_map`); every results row records the mapping its cell used, in the
canonical text `format_camera_map` writes (the same syntax the flag takes).

Plain names and strings only: stage 1 (extract of native towers) and stage 2 (fit) both check with it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from graftcache.errors import GraftcacheError

FLAG = "--camera-map"
SYNTAX = "POLICY=CACHE[,POLICY=CACHE...]"


class CameraError(GraftcacheError):
    """A policy's cameras and a cache's (or dataset's) cameras that cannot be paired as asked."""


def parse_camera_map(text: str) -> dict[str, str]:
    """`"image=agentview,image2=eye_in_hand"` -> {"image": "agentview", "image2": "eye_in_hand"}. A part that is
    not POLICY=CACHE, a policy camera named twice, or one cache camera feeding two policy cameras is an error."""
    pairs: dict[str, str] = {}
    for part in text.split(","):
        policy, eq, cache = (s.strip() for s in part.partition("="))
        if not (eq and policy and cache):
            raise CameraError(f"camera map {text!r}: {part.strip()!r} is not POLICY=CACHE (syntax {SYNTAX})")
        if policy in pairs:
            raise CameraError(f"camera map {text!r}: policy camera {policy!r} is mapped twice")
        pairs[policy] = cache
    for cache in dict.fromkeys(pairs.values()):
        slots = [p for p, c in pairs.items() if c == cache]
        if len(slots) > 1:
            raise CameraError(f"camera map {text!r}: cache camera {cache!r} would feed policy cameras "
                              f"{', '.join(slots)}; map each policy camera from a camera of its own")
    return pairs


def valid_camera_map(text: str) -> bool:
    """Whether `text` parses (the request's range rule; the CLI's parser names the problem)."""
    try:
        parse_camera_map(text)
    except CameraError:
        return False
    return True


def format_camera_map(mapping: Mapping[str, str]) -> str:
    """The canonical text of a mapping, in the policy's camera order: `image=agentview,image2=eye_in_hand`."""
    return ",".join(f"{policy}={cache}" for policy, cache in mapping.items())


def renames(mapping: Mapping[str, str]) -> bool:
    """Whether some policy camera is fed by a cache camera of another name."""
    return any(policy != cache for policy, cache in mapping.items())


def _example(policy: Sequence[str], cache: Sequence[str]) -> str:
    """A complete map to show in an error: namesakes kept, the other slots given the unused cameras in order."""
    spare = iter([c for c in cache if c not in policy])
    pairs = {p: p if p in cache else next(spare, None) for p in policy}
    if None in pairs.values():
        return ""
    return f", e.g. {FLAG} {format_camera_map(pairs)}"


def match_cameras(policy: Sequence[str], cache: Sequence[str], given: str | None, *, policy_name: str,
                  cache_name: str) -> dict[str, str]:
    """Policy camera -> the cache camera that feeds it, in the policy's order.

    Without `given`, every policy camera must be a cache camera of the same name (extra cache cameras are
    simply not read). With it, `given` must map every policy camera, name only cameras of the two sides, and
    feed each policy camera from a camera of its own. Every refusal is one line naming both sides' cameras.
    """
    sides = f"policy {policy_name} has camera(s) {', '.join(policy)}; {cache_name} has {', '.join(cache) or 'none'}"
    if given is None:
        if all(p in cache for p in policy):
            return {p: p for p in policy}
        raise CameraError(f"camera names differ ({sides}): pass {FLAG} {SYNTAX} to say which camera feeds each "
                          f"policy camera{_example(policy, cache)} (in a sweep recipe: camera_map)")
    pairs = parse_camera_map(given)
    unknown = [p for p in pairs if p not in policy]
    if unknown:
        raise CameraError(f"camera map {given!r} names policy camera {unknown[0]!r}, which the policy lacks ({sides})")
    missing = [c for c in pairs.values() if c not in cache]
    if missing:
        raise CameraError(f"camera map {given!r} names camera {missing[0]!r}, which {cache_name} lacks ({sides})")
    unmapped = [p for p in policy if p not in pairs]
    if unmapped:
        raise CameraError(f"camera map {given!r} leaves policy camera(s) {', '.join(unmapped)} unmapped: map every "
                          f"one ({sides})")
    return {p: pairs[p] for p in policy}
