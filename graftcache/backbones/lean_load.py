"""Lean loading: a lerobot policy built with no memory for its weights, then filled from its checkpoint tensor
by tensor, straight onto the target device in each parameter's own dtype.

Why not lerobot's `from_pretrained`: it constructs and randomly initialises every parameter in fp32 (pi0.5:
4.1B parameters, 16.6 GB), casts the LM to bf16, reads the whole checkpoint into a second state dict and copies
it over: more host memory than the policy twice over, and minutes of copying (docs/measured.md). Here:

- `construct` runs the policy's own constructor with every parameter created on the meta device
  (`parameters_on_meta`), so names, shapes, dtypes (pi0.5's bf16 LM beside its fp32 vision path and norms),
  requires_grad flags and tied weights are lerobot's own, and initialising them touches no memory. Buffers are
  created for real, on the CPU, by the constructor itself: the non-persistent ones (rotary `inv_freq`, position
  ids), which no checkpoint holds, are exactly what lerobot computes.
- `load_checkpoint` maps every parameter and persistent buffer to a checkpoint key (`keys`: a policy may rename
  keys on load, as pi0.5 does), refuses a checkpoint that lacks one or shapes one differently (lerobot's own
  loads only log missing keys, or return a partly random model), then reads each tensor with plain file reads,
  not a memory map, so the file's pages never count against the process. On a CPU a tensor already in its
  parameter's dtype is read straight into its own memory; any other (a cast, a GPU) passes through one reused
  host buffer the size of the largest such tensor (pinned for CUDA): the host holds the model (CPU) or nothing
  of it (GPU) plus that buffer.
"""

from __future__ import annotations

import contextlib
import json
import struct
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import torch
from torch import nn

from graftcache.backbones.patching import patched
from graftcache.errors import BackboneError

#: safetensors dtype names (the format's header) -> torch dtypes.
DTYPES = {"F64": torch.float64, "F32": torch.float32, "BF16": torch.bfloat16, "F16": torch.float16,
          "I64": torch.int64, "I32": torch.int32, "I16": torch.int16, "I8": torch.int8, "U8": torch.uint8,
          "BOOL": torch.bool}

#: lerobot's internals this module reaches (graftcache.backbones.spec.BackboneSpec.lerobot_reaches says why they are
#: declared): the openpi ports' key fix-up `openpi_keys` calls, one per PaliGemma policy.
LEROBOT_REACHES = (
    "lerobot.policies.pi0.modeling_pi0.PI0Policy._fix_pytorch_state_dict_keys",
    "lerobot.policies.pi05.modeling_pi05.PI05Policy._fix_pytorch_state_dict_keys",
    "lerobot.policies.pi0_fast.modeling_pi0_fast.PI0FastPolicy._fix_pytorch_state_dict_keys",
)


@contextlib.contextmanager
def parameters_on_meta() -> Iterator[None]:
    """Every parameter registered meanwhile moves to the meta device (its dtype and requires_grad kept); a
    parameter already there is kept as it is, so weights tied by assignment stay one object."""
    register = nn.Module.register_parameter

    def on_meta(module: nn.Module, name: str, param: nn.Parameter | None) -> None:
        if param is not None and param.device.type != "meta":
            param = nn.Parameter(param.detach().to("meta"), requires_grad=param.requires_grad)
        register(module, name, param)

    with patched(nn.Module, register_parameter=on_meta):
        yield


def construct(build: Callable[[], nn.Module], config) -> nn.Module:
    """`build()` (a policy constructor reading `config`) with its parameters on the meta device and no
    initialisation run (transformers' `no_init_weights`: on meta tensors it computes nothing, slowly:
    docs/measured.md). lerobot's policies move themselves to `config.device`, which a meta parameter cannot leave:
    it is None meanwhile."""
    from transformers.initialization import no_init_weights

    with patched(config, device=None), parameters_on_meta(), no_init_weights():
        return build()


def read_header(path: Path) -> tuple[int, dict[str, dict]]:
    """(offset of the data, {key: {"dtype", "shape", "data_offsets"}}) of a safetensors file (8-byte
    little-endian header length, then the JSON header, then the data)."""
    with path.open("rb") as f:
        (length,) = struct.unpack("<Q", f.read(8))
        header = json.loads(f.read(length))
    header.pop("__metadata__", None)
    return 8 + length, header


def openpi_keys(policy: nn.Module, file_keys: Iterable[str]) -> dict[str, str]:
    """{policy key: file key} as the openpi ports' `from_pretrained` (pi0, pi0.5) renames: the policy's own
    `_fix_pytorch_state_dict_keys`, then a "model." prefix, a later key winning a clash as it does there."""

    class Source(str):
        def clone(self) -> Source:  # the fix-up clones lm_head into embed_tokens: the same file key
            return self

    fixed = policy._fix_pytorch_state_dict_keys({k: Source(k) for k in file_keys}, policy.config)
    return {k if k.startswith("model.") else f"model.{k}": str(v) for k, v in fixed.items()}


def _reads(policy: nn.Module, path: Path, header: dict[str, dict], keys: dict[str, str]) -> list[tuple[str, list[str]]]:
    """[(file key, policy names sharing one tensor)] in file order; BackboneError unless every tensor of the
    state dict has a same-shaped entry. Of tied names, the last one the checkpoint holds is read (as
    load_state_dict, copying in state-dict order, leaves it)."""
    state = policy.state_dict(keep_vars=True)  # parameters and persistent buffers, tied names each listed
    tied: dict[int, list[str]] = {}
    for name, tensor in state.items():
        tied.setdefault(id(tensor), []).append(name)
    reads, missing, wrong = [], [], []
    for names in tied.values():
        found = [n for n in names if keys.get(n) in header]
        if not found:
            missing.extend(names)
            continue
        key = keys[found[-1]]
        if tuple(header[key]["shape"]) != tuple(state[names[0]].shape):
            wrong.append(f"{names[0]} {tuple(state[names[0]].shape)} vs {tuple(header[key]['shape'])}")
        reads.append((key, names))
    if missing or wrong:
        unexpected = [k for k in keys if k not in state]  # named only: lerobot drops some keys on purpose
        detail = "; ".join([*(f"missing {k}" for k in missing[:3]), *(f"shape {w}" for w in wrong[:3]),
                            *(f"unexpected {k}" for k in unexpected[:3])])
        raise BackboneError(f"{path}: checkpoint does not match the policy ({len(missing)} missing, {len(wrong)} "
                            f"mis-shaped, {len(unexpected)} unexpected): {detail}")
    return sorted(reads, key=lambda entry: header[entry[0]]["data_offsets"][0])


def read_into(f, offset: int, target: torch.Tensor) -> None:
    """Fill the host tensor `target` with its bytes, read at `offset` of the file."""
    view = memoryview(target.view(-1).view(torch.uint8).numpy())
    f.seek(offset)
    done = 0
    while done < len(view):
        n = f.readinto(view[done:])
        if not n:
            raise BackboneError(f"{f.name}: truncated (ends inside tensor data)")
        done += n


def _set(policy: nn.Module, name: str, value: torch.Tensor) -> None:
    module_name, _, local = name.rpartition(".")
    module = policy.get_submodule(module_name)
    slots = module._parameters if local in module._parameters else module._buffers
    slots[local] = value


@torch.no_grad()
def load_checkpoint(policy: nn.Module, path: Path, keys: dict[str, str], device: torch.device) -> None:
    """Fill a policy built by `construct` from the safetensors file `path` ({policy key: file key} `keys`),
    each tensor cast to its parameter's dtype (as load_state_dict's copy casts) and moved to `device`; the
    constructor's own buffers follow it there."""
    start, header = read_header(path)
    reads = _reads(policy, path, header, keys)
    state = policy.state_dict(keep_vars=True)

    def direct(key: str, names: list[str]) -> bool:  # read into its own memory, nothing copied after
        return device.type == "cpu" and DTYPES[header[key]["dtype"]] == state[names[0]].dtype

    def nbytes(key: str) -> int:
        begin, end = header[key]["data_offsets"]
        return end - begin

    # Every other tensor (a cast, another device) passes through one reused host buffer, pinned for CUDA.
    staging = torch.empty(max((nbytes(k) for k, names in reads if not direct(k, names)), default=0),
                          dtype=torch.uint8, pin_memory=device.type == "cuda")
    with path.open("rb", buffering=0) as f:
        for key, names in reads:
            entry, like = header[key], state[names[0]]
            dtype, offset = DTYPES[entry["dtype"]], start + entry["data_offsets"][0]
            if direct(key, names):
                value = torch.empty(entry["shape"], dtype=dtype)
                read_into(f, offset, value)
            else:
                host = staging[:nbytes(key)].view(dtype).reshape(entry["shape"])
                read_into(f, offset, host)
                value = host.to(device=device, dtype=like.dtype)  # a new tensor: a cast or a copy to the device
            if isinstance(like, nn.Parameter):
                value = nn.Parameter(value, requires_grad=like.requires_grad)
            for name in names:
                _set(policy, name, value)
    moved: dict[int, torch.Tensor] = {}
    for module in policy.modules():
        for local, buffer in module._buffers.items():
            if buffer is not None and buffer.device != device:
                module._buffers[local] = moved.setdefault(id(buffer), buffer.to(device))
    left = [n for n, t in (*policy.named_parameters(), *policy.named_buffers()) if t.is_meta]
    if left:
        raise BackboneError(f"{path}: {len(left)} policy tensors were neither in the checkpoint nor built by the "
                            f"constructor, e.g. {left[0]}")
