"""Policy batches: raw batches through lerobot's preprocessor, prompt tokens made once per task.

Tokenising the same few task strings for every batch costs more than a grafted step on the tiny
backbones, so where the prompt does not embed the state (SmolVLA) each distinct task is tokenised once
and padded the way lerobot's tokenizer step pads a batch; pi0.5's prompt embeds the state, so it is
tokenised per batch by the preprocessor itself.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from graftcache.errors import BackboneError
from graftcache.graft import feature_key

TOKENS = "observation.language.tokens"
TOKEN_MASK = "observation.language.attention_mask"
STATE = "observation.state"
ACTION = "action"
ACTION_PAD = "action_is_pad"


class PromptBatches:
    """The batch half of a BackboneAdapter (mixed into it; uses its preprocessor, cameras and device)."""

    def prepare(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        """Raw batch -> policy batch via lerobot's preprocessor (normalisation, tokens, device).

        `raw` holds `observation.vis_feats.<camera>` [B, T, C] (grafted) or `observation.images.<camera>`
        [B, 3, H, W] in [0, 1] (native policy), `observation.state` [B, S] and `task` (list of B
        strings), plus for training `action` [B, chunk, A] and `action_is_pad` [B, chunk].
        """
        batch = dict(raw)
        wanted = [feature_key(k) if self.grafted else k for k in self.camera_keys] + [STATE, "task"]
        missing = [k for k in wanted if k not in batch]
        if missing:
            raise BackboneError(f"{self.name} batch is missing {', '.join(missing)}")
        if self.prompt_uses_state:
            return self.preprocessor(batch)
        tasks = batch.pop("task")
        tasks = [tasks] if isinstance(tasks, str) else list(tasks)
        out = self._preprocessor_without_tokens(batch)
        ids, mask = self.task_tokens(tasks)
        out[TOKENS], out[TOKEN_MASK], out["task"] = ids.to(self.device), mask.to(self.device), tasks
        return out

    @functools.cached_property
    def _token_steps(self) -> list:
        return [s for s in self.preprocessor.steps if type(s).__name__ in self.token_steps]

    @functools.cached_property
    def _preprocessor_without_tokens(self):
        pre = self.preprocessor
        steps = [s for s in pre.steps if type(s).__name__ not in self.token_steps]
        return type(pre)(steps=steps, name=pre.name, to_transition=pre.to_transition, to_output=pre.to_output)

    def task_tokens(self, tasks: Sequence[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """Token ids [N, L] and attention mask [N, L] for task strings, tokenised once per distinct task.

        Padding follows the preprocessor's tokenizer step (e.g. SmolVLA pads to the longest prompt of
        the batch), so the result equals lerobot's own per-batch tokenisation.
        """
        if self.prompt_uses_state:
            raise BackboneError(f"{self.name} prompts embed the discretised state: tokenise per batch with prepare()")
        from lerobot.processor import TransitionKey
        from lerobot.processor.converters import create_transition

        for task in dict.fromkeys(tasks):
            if task not in self._task_cache:
                transition = create_transition(observation={}, complementary_data={"task": [task]})
                for step in self._token_steps:
                    transition = step(transition)
                obs = transition[TransitionKey.OBSERVATION]
                self._task_cache[task] = (obs[TOKENS][0].cpu(), obs[TOKEN_MASK][0].cpu())
        tokenizer_step = self._token_steps[-1]
        rows = [self._task_cache[t] for t in tasks]
        length = max(len(ids) for ids, _ in rows)
        ids = torch.full((len(rows), length), tokenizer_step.input_tokenizer.pad_token_id, dtype=torch.long)
        mask = torch.zeros((len(rows), length), dtype=torch.bool)
        for i, (row_ids, row_mask) in enumerate(rows):
            right = tokenizer_step.padding_side == "right"
            cols = slice(0, len(row_ids)) if right else slice(length - len(row_ids), length)
            ids[i, cols], mask[i, cols] = row_ids, row_mask
        return ids, mask
