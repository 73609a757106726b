"""Tiny and released Wall-X configurations (lerobot 0.6 `WallXConfig`: Qwen2.5-VL ViT + a hard-routed MoE Qwen2.5
LM + a flow action head), buildable offline.

`WallXPolicy.__init__` always calls `Qwen2_5_VLMoEForAction.from_pretrained(config.pretrained_name_or_path)`, which
reads three things from that hub repo (x-square-robot/wall-oss-flow): the Qwen2.5-VL config with Wall-X's MoE fields
(`config.json`), the processor (`AutoProcessor`: tokenizer with Wall-X's `<|propri|>` / `<|action|>` tokens, Qwen's
image processor), and the base weights (`model.safetensors`). A lerobot checkpoint of the policy holds the weights
of the whole policy, so `from_config` below does the first two reads and the construction exactly as lerobot's
`from_pretrained` does, and skips the third (the checkpoint's weights follow).

The tiny folder graftcache/resources/tiny/wall_x/ holds only the tiny MoE config (generated once by
`python -m graftcache.backbones.wall_x.tiny`); its processor is EO-1's tiny Qwen2.5-VL one
(graftcache/resources/tiny/qwen2_5_vl/) with the tokens wall-x's scripts/merge_tokenizer.py adds to Qwen's
tokenizer (`<|propri|>`, `<|action|>`; no FAST tokens: graftcache runs Wall-X's flow mode) and its left padding.

- tiny: vision tower 32 wide x 2 blocks (EO-1's tiny ViT), merger into a Qwen2.5 text model 64 wide x 2 layers
  whose MLP is Wall-X's two experts (VLM tokens: 128 wide, action tokens: 64 wide); Wall-X resizes every frame to
  256 px (252 after smart_resize), the tiny processor bounds it to 16 x 28*28 pixels: 112 px -> 8x8 patches ->
  2x2 merge -> 4x4 = 16 tokens per camera.
- released (x-square-robot/wall-oss-flow, lerobot's default `pretrained_name_or_path`): Qwen2.5-VL-3B's ViT
  (1280 wide x 32 blocks) and 36-layer 2048-wide LM, the second expert 2048 -> 2048 for the action tokens
  (wall-x's workspace/models_config/qwen2_5_moe_flash.json), 20 action and 20 proprioception dims (lerobot's
  `max_action_dim` / `max_state_dim`, the sizes of the action head's input projections); Qwen's own pixel
  bounds: 256 px -> 252 -> 18x18 patches -> 9x9 = 81 tokens per camera. The hub repo is unreachable here: its
  config and vocabulary (`WALL_OSS_VOCAB`) are reconstructed from wall-x's public repo, not read from it.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from pathlib import Path

from graftcache.backbones.patching import patched
from graftcache.backbones.tiny import TinyBuild, action_features, build_seeded, visual_features
from graftcache.backbones.tiny_assets import QWEN25_VL_3B, QWEN_VL_DIR, TINY_QWEN25_VL, TINY_ROOT, qwen25_vl_ids
from graftcache.errors import BackboneError

WALLX_DIR = TINY_ROOT / "wall_x"
TINY_IMAGE_SIZE = 128  # what train-tiny resizes frames to (requests.TinyTrainConfig.image_size)
#: What wall-x's scripts/merge_tokenizer.py adds to Qwen's tokenizer for the flow mode (the FAST tokens aside).
WALLX_TOKENS = ("<|propri|>", "<|action|>")
#: The 20 action dims of wall-oss-flow's `dof_config` (wall-x's default robot config); proprioception likewise.
WALLX_DOFS = {"follow_left_ee_cartesian_pos": 3, "follow_left_ee_rotation": 3, "follow_left_gripper": 1,
              "follow_right_ee_cartesian_pos": 3, "follow_right_ee_rotation": 3, "follow_right_gripper": 1,
              "head_actions": 2, "height": 1, "car_pose": 3}
NOISE_SCHEDULER = {"beta_alpha": 1.5, "beta_beta": 1.0, "t_eps": 0.001, "s": 0.999, "num_inference_timesteps": 10}


def _moe(width: int, vlm_mlp: int, action_mlp: int) -> dict:
    """Wall-X's MLP experts: expert 0 for the VLM tokens, expert 1 for the action tokens (moe_token_types)."""
    experts = [{"hidden_size": width, "intermediate_size": mlp, "hidden_act": "silu"} for mlp in (vlm_mlp, action_mlp)]
    return {"num_experts": 2, "experts": experts, "dim_inputs": [width, width], "mlp_moe": True,
            "attention_moe": False, "dof_config": dict(WALLX_DOFS), "agent_pos_config": dict(WALLX_DOFS),
            "noise_scheduler": dict(NOISE_SCHEDULER)}


def _with_moe(qwen: dict, moe: dict) -> dict:
    text = {**qwen["text_config"], **{k: v for k, v in moe.items() if k != "agent_pos_config"}}
    return {**qwen, "text_config": text, "agent_pos_config": moe["agent_pos_config"]}


#: x-square-robot/wall-oss-flow: Qwen2.5-VL-3B with Wall-X's action expert.
WALL_OSS_FLOW = _with_moe(QWEN25_VL_3B, _moe(2048, 11008, 2048))
#: Qwen2.5-VL's 151665 tokens + <|propri|>, <|action|> + FAST's 2048 action tokens (wall-x's merge_tokenizer.py):
#: the vocabulary `from_pretrained` resizes the embedding to.
WALL_OSS_VOCAB = 151_665 + len(WALLX_TOKENS) + 2048


def write_wallx_config(out: Path = WALLX_DIR) -> Path:
    """Write the tiny Wall-X Qwen2.5-VL MoE config (token ids from the tiny Qwen tokenizer)."""
    from lerobot.policies.wall_x.qwen_model import Qwen2_5_VLConfig

    out.mkdir(parents=True, exist_ok=True)
    moe = _moe(TINY_QWEN25_VL["text_config"]["hidden_size"], 128, 64)
    Qwen2_5_VLConfig(**_with_moe(qwen25_vl_ids(), moe)).save_pretrained(out)
    return out


def tiny_processor():
    """The tiny Qwen2.5-VL processor with Wall-X's tokens added and left padding, as merge_tokenizer.py does."""
    from transformers import AutoProcessor

    processor = AutoProcessor.from_pretrained(QWEN_VL_DIR, use_fast=True)
    processor.tokenizer.add_tokens(list(WALLX_TOKENS))
    processor.tokenizer.padding_side = "left"
    return processor


def load_processor(folder: Path):
    """Wall-X's processor for `folder`: the tiny one, or the folder's own (lerobot's `AutoProcessor` call)."""
    from transformers import AutoProcessor

    if folder == WALLX_DIR:
        return tiny_processor()
    return AutoProcessor.from_pretrained(folder, use_fast=True)


def from_config(cls, pretrained_name_or_path, action_tokenizer_path=None, attn_implementation: str = "eager",
                vision_attn_implementation: str = "auto"):
    """`Qwen2_5_VLMoEForAction.from_pretrained` without its weight read: config and processor from the folder,
    the model built and its embedding resized to the tokenizer, as lerobot's own does."""
    if action_tokenizer_path is not None:
        raise BackboneError(f"wall_x: FAST mode needs the hub action tokenizer {action_tokenizer_path!r}; graftcache "
                            "runs Wall-X's flow (prediction_mode='diffusion') only")
    folder = Path(pretrained_name_or_path)
    config = cls.config_class.from_pretrained(folder)
    config._attn_implementation = attn_implementation
    processor = load_processor(folder)
    config.pad_token_id = config.text_config.pad_token_id = processor.tokenizer.pad_token_id
    model = cls(config, processor=processor, action_tokenizer=None,
                vision_attn_implementation=vision_attn_implementation)
    model.resize_token_embeddings(len(processor.tokenizer))
    return model


@contextlib.contextmanager
def built_from(folder: Path) -> Iterator[None]:
    """While open, `WallXPolicy(config)` builds its model with `from_config` from `folder` (config.json +
    processor) whatever `config.pretrained_name_or_path` names."""
    from lerobot.policies.wall_x import modeling_wall_x

    def build(cls, pretrained_name_or_path, **kwargs):
        return from_config(cls, folder, **kwargs)

    with patched(modeling_wall_x.Qwen2_5_VLMoEForAction, from_pretrained=classmethod(build)):
        yield


def construct(config, folder: Path):
    """WallXPolicy(config) with its model from `folder` (no weights read)."""
    from lerobot.policies.wall_x.modeling_wall_x import WallXPolicy

    with built_from(folder):
        return WallXPolicy(config)


def wallx_tiny_config(tiny: TinyBuild, device: str, image_size: int = TINY_IMAGE_SIZE):
    """Tiny Wall-X at the dataset's `image_size` (lerobot's defaults otherwise: 20-dim padded state and action)."""
    from lerobot.policies.wall_x.configuration_wall_x import WallXConfig

    return WallXConfig(pretrained_name_or_path=str(WALLX_DIR), device=device, chunk_size=tiny.chunk_size,
                       n_action_steps=tiny.chunk_size, input_features=visual_features(tiny, image_size),
                       output_features=action_features(tiny))


def wallx_released_config(cameras: tuple[str, ...], image_size: int, state_dim: int, action_dim: int, device: str):
    """lerobot's Wall-X defaults for a dataset (x-square-robot/wall-oss-flow, chunk 32, flow mode)."""
    from lerobot.policies.wall_x.configuration_wall_x import WallXConfig

    tiny = TinyBuild(cameras=cameras, state_dim=state_dim, action_dim=action_dim)
    return WallXConfig(device=device, input_features=visual_features(tiny, image_size),
                       output_features=action_features(tiny))


def build_tiny(tiny: TinyBuild, stats: dict | None, device: str):
    """Random-init tiny Wall-X, its model from the shipped tiny folder, and its processors
    (graftcache.backbones.tiny.build_seeded)."""
    from lerobot.policies.wall_x.processor_wall_x import make_wall_x_pre_post_processors

    return build_seeded(tiny, stats, device, wallx_tiny_config(tiny, device),
                        lambda config: construct(config, WALLX_DIR), make_wall_x_pre_post_processors)


if __name__ == "__main__":
    folder = write_wallx_config()
    print(folder, json.loads((folder / "config.json").read_text())["text_config"]["experts"])
