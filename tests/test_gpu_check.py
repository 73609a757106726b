"""benchmarks/gpu_check.py's CPU dry run (`--tiny --device cpu`): every stage's code runs on the tiny backbones, so
the check's first run on a lent GPU cannot fail on a typo; its JSON must say what each stage measured and add up."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from graftcache.backbone_registry import BACKBONES

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _gpu_check(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    monkeypatch.delitem(sys.modules, "gpu_check", raising=False)
    import gpu_check

    return gpu_check


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    with pytest.MonkeyPatch.context() as mp:
        gpu_check = _gpu_check(mp)
        tmp = tmp_path_factory.mktemp("gpu-check")
        out = tmp / "check.json"
        data = gpu_check.main(["--tiny", "--device", "cpu", "--compute-dtype", "fp32", "--repeats", "1",
                               "--encoders", "dinov2-s", "--budget-s", "3600", "--scratch", str(tmp / "scratch"),
                               # issue 42's stages cut to one batch, two cell counts and dynamo's capture alone
                               # (tests/backbones/test_compiled.py checks a compiled backend's numbers)
                               "--plan-batches", "2", "--fused-batches", "2", "--cells", "1,2",
                               "--card-backbones", "pi05",
                               "--compile-backend", "eager", "--compile-backbones", "pi05", "--out", str(out)])
    return data, out


@pytest.mark.slow
def test_every_backbone_passes_the_correctness_stage(report: tuple[dict, Path]) -> None:
    data, out = report
    assert json.loads(out.read_text())["done"] is True and data["done"] is True
    head = data["header"]
    assert head["device"] == "cpu" and head["tiny"] is True and head["random_init"] is True
    assert head["torch"] and head["lerobot"] and head["cpu"] and isinstance(head["cpu_avx512_bf16"], bool)
    tiny = data["stages"]["1_tiny"]
    assert set(tiny) == set(BACKBONES)
    for name, entry in tiny.items():
        assert entry["status"] == "ok", (name, entry)
        assert entry["fused_ok"] and entry["checkpointing_ok"] and entry["lean_ok"] and entry["compute_dtype_ok"]
        if "plans_checked" in entry:  # every recompute plan but off, against off
            assert entry["plans_checked"][-1] == "on" and entry["checkpointing_max_rel_diff"] < 1e-4
        assert entry["native_ok"] and entry["native_encoder_on"] == ["cpu"]
        assert entry["lean_same_sha256"] is True and entry["params"] > 0
        if "fused_max_rel_diff" in entry:  # a backbone whose cells share passes
            assert entry["fused_max_rel_diff"] < 1e-4 and len(entry["fused_losses"]) == 2
    assert "not fusable" in tiny["pi0_fast"]["fused"]  # one loss a batch: its cells run alone


@pytest.mark.slow
def test_released_stages_measure_steps_flops_and_cells_per_hour(report: tuple[dict, Path]) -> None:
    data, _ = report
    stages = data["stages"]
    for stage, batches in (("2_pi05", (2, 4)), ("3_smolvla", (2, 4))):
        flops = stages[stage]["flops"]
        assert flops["step_flops"] > 0 and flops["flops_per_sample"] == flops["step_flops"] / batches[0]
        for batch in batches:
            for ckpt in ("off", "on"):
                entry = stages[stage][f"batch{batch}_ckpt_{ckpt}"]
                assert entry["status"] == "ok" and entry["step_s"] > 0 and entry["batch"] == batch
                assert entry["checkpointing"] is (ckpt == "on")
                assert entry["peak_gb"] is None and entry["mfu"] is None  # a CPU: no device memory, no peak
    smol = stages["3_smolvla"]
    for n in (1, 2, 4):
        entry = smol[f"cells_per_pass_{n}"]
        assert entry["cells"] == n and entry["cell_step_s"] == pytest.approx(entry["step_s"] / n)
        assert entry["training_cells_per_gpu_hour"] == pytest.approx(3600 / (2000 * entry["cell_step_s"]))
    load = stages["4_lean_load"]
    assert load["save"]["checkpoint_gb"] > 0 and load["load"]["status"] == "ok"
    assert load["load"]["params_on"] == ["cpu"] and load["load"]["load_s"] > 0
    assert load["load"]["peak_rss_gb"] >= load["load"]["rss_before_gb"]


@pytest.mark.slow
def test_the_protocol_projection_adds_up_and_the_zoo_says_what_it_skipped(report: tuple[dict, Path]) -> None:
    data, _ = report
    protocol = data["stages"]["5_protocol"]
    assert protocol["recipe"]["recipe"] == "cli/paper.toml"
    kinds = [v for k, v in protocol.items() if k.startswith(("smolvla_", "pi05_"))]
    assert kinds and all(k["status"] == "ok" and k["eval_s_per_frame"] > 0 for k in kinds)
    assert any(k["lora"] for k in kinds) and any(not k["train"] for k in kinds)
    hours = protocol["projection"]
    assert hours["projected_h"] == pytest.approx(hours["loads_h"] + hours["training_h"] + hours["evaluation_h"])
    assert hours["flop_bound_h_40"] == pytest.approx(hours["flop_bound_h_100"] / 0.4)
    # paper.toml with one encoder: 2 backbones x 2 suites x 3 seeds x (the plain graft + 5 encoder-reading
    # controls + the 2 native ones)
    assert protocol["recipe"]["encoders"] == ["dinov2-s"] and hours["rows"] == 2 * 2 * 3 * (1 + 5 + 2)
    zoo = data["stages"]["6_zoo"]
    assert zoo["pi0"]["status"] == "ok" and zoo["pi0"]["step_s"] > 0 and zoo["pi0"]["step_flops"] > 0
    skipped = set(BACKBONES) - {"smolvla", "pi05", "pi0"}
    assert {n for n, e in zoo.items() if e["status"] == "skipped"} == skipped
    assert all("no released-geometry builder" in zoo[n]["reason"] for n in skipped)


@pytest.mark.slow
def test_issue_42_stages_measure_each_plan_attention_path_cells_and_compile(report: tuple[dict, Path]) -> None:
    stages = report[0]["stages"]
    pi05 = stages["7_pi05_plans"]
    for attention in ("eager", "sdpa"):
        estimate = pi05[f"estimate_{attention}"]
        assert estimate["status"] == "ok" and estimate["batch"] == 2 and estimate["attention"] == attention
        for plan in ("off", "mlp", "on"):  # measured, not modelled: bytes and FLOPs of real steps under each plan
            assert estimate[plan]["one_frame_gb"] > 0 and estimate[plan]["per_frame_gb"] > 0
            assert estimate[plan]["step_flops"] > 0 and estimate[plan]["basis"].startswith("autograd saved bytes")
        # the plans ranked as their estimates say: more recompute, fewer bytes a frame
        assert estimate["ranked_ok"] and estimate["by_per_frame_bytes"] == estimate["by_recompute"] == [
            "off", "mlp", "on"]
        assert estimate["off"]["recompute_fraction"] == 0
        assert 0 < estimate["mlp"]["recompute_fraction"] < estimate["on"]["recompute_fraction"]
        assert estimate["auto_on_card"] == {"batch2": "off"}  # a tiny step fits any card
        for plan in ("off", "mlp", "on"):
            entry = pi05[f"batch2_{attention}_{plan}"]
            assert entry["status"] == "ok" and entry["step_s"] > 0 and entry["loss_finite"]
            assert (entry["batch"], entry["plan"], entry["attention"]) == (2, plan, attention)
            assert entry["estimate_gb"] == pytest.approx(estimate[plan]["one_frame_gb"]
                                                         + estimate[plan]["per_frame_gb"], abs=1e-4)
    # the fused path keeps no score matrices: fewer bytes a frame than eager under the plan that keeps everything
    assert pi05["estimate_sdpa"]["off"]["per_frame_gb"] < pi05["estimate_eager"]["off"]["per_frame_gb"]
    smol = stages["8_smolvla_fused"]
    for attention in ("eager", "sdpa"):
        for n in (1, 2):
            entry = smol[f"{attention}_batch2_cells{n}"]
            assert entry["status"] == "ok" and entry["cells"] == n and entry["plan"] == "off"
            assert entry["attention"] == attention and entry["batch"] == 2
            assert entry["cell_step_s"] == pytest.approx(entry["step_s"] / n)
            assert entry["training_cells_per_gpu_hour"] == pytest.approx(3600 / (2000 * entry["cell_step_s"]))
    compiled = stages["10_compile"]["pi05_batch2_cells1"]
    assert compiled["status"] == "ok" and compiled["backend"] == "eager" and compiled["graphs"] >= 1
    assert compiled["eager_step_s"] > 0 and compiled["compiled_step_s"] > 0 and compiled["compile_s"] > 0
    assert compiled["saved_s_per_step"] == pytest.approx(compiled["eager_step_s"] - compiled["compiled_step_s"])
    assert compiled["plan"] == "off" and compiled["graph_breaks"] >= 0
    card = stages["9_protocol_80gb"]
    assert card["card"]["cap"] == "cpu: no device memory to cap" and card["card"]["card_gib"] == 79.1
    assert card["card"]["attention"] == "auto" == card["recipe"]["attention"]
    assert card["recipe"]["attention_resolved"] == {"pi05": "sdpa"}  # --card-backbones pi05: the recipe's pi05 alone
    assert stages["5_protocol"]["recipe"]["attention_resolved"] == {"pi05": "eager", "smolvla": "eager"}
    kinds = [v for k, v in card.items() if k.startswith(("smolvla_", "pi05_"))]
    assert kinds and all(k["status"] == "ok" and k["eval_s_per_frame"] > 0 for k in kinds)
    assert {k for k in card if k.startswith("pi05_")} == {k for k in stages["5_protocol"] if k.startswith("pi05_")}
    assert not any(k.startswith("smolvla_") for k in card)
    hours = card["projection"]
    assert hours["projected_h"] == pytest.approx(hours["loads_h"] + hours["training_h"] + hours["evaluation_h"])
    assert hours["rows"] == 2 * 3 * (1 + 5 + 2)  # one backbone of the paper's two


def test_a_spent_budget_skips_every_stage_and_still_writes_the_json(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    gpu_check = _gpu_check(monkeypatch)
    out = tmp_path / "check.json"
    data = gpu_check.main(["--tiny", "--device", "cpu", "--budget-s", "0", "--backbones", "smolvla",
                           "--stages", "1,2", "--scratch", str(tmp_path / "scratch"), "--out", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(data, default=str))
    checks = [e for stage in data["stages"].values() for e in stage.values()]
    assert checks and all(e["status"] == "skipped" and e["reason"].startswith("budget") for e in checks)
    assert data["done"] is True


@pytest.mark.parametrize("name", ["pi05", "pi0"])
def test_on_device_builds_the_geometry_lerobot_constructs(name: str, tmp_path: Path) -> None:
    """devtools.released.on_device (stages 2 and 6 on a GPU) at the released geometry, on the meta device: the
    parameters lerobot's own constructor makes (names and shapes), in the dtypes lerobot leaves them (bf16 LM, fp32
    connector), the policy's processors built with the tokenizer from the hub cache, labelled random-init."""
    import torch
    from lerobot.policies.factory import get_policy_class

    from devtools.released import CONFIGS, _construct_on_meta, hub_cache, on_device

    adapter = on_device(name, "meta", cache=tmp_path)
    with hub_cache(tmp_path):
        reference = _construct_on_meta(get_policy_class(name), CONFIGS[name](tmp_path))
    params = dict(adapter.policy.named_parameters())
    assert {n: tuple(p.shape) for n, p in params.items()} == {
        n: tuple(p.shape) for n, p in reference.named_parameters()}
    assert {p.device.type for p in (*params.values(), *adapter.policy.buffers())} == {"meta"}
    vlm = "model.paligemma_with_expert.paligemma.model"
    assert params[f"{vlm}.language_model.layers.0.mlp.up_proj.weight"].dtype == torch.bfloat16
    assert params[f"{vlm}.multi_modal_projector.linear.weight"].dtype == torch.float32
    assert adapter.random_init and "random init on meta" in adapter.source
    assert adapter.token_grid == (16, 16) and adapter.lm_width == 2048 and adapter.preprocessor is not None
