"""graftcache.graft: the projector, the pass-through tower, freezing and the freeze report."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from graftcache.backbones.surgery import FreezeReport, PassThroughTower, freeze_all_but, freeze_report
from graftcache.graft import FusedProjector, GraftProjector, PassThroughProjector, at_width, feature_key


def test_feature_key_strips_the_image_prefix() -> None:
    assert feature_key("image2") == "observation.vis_feats.image2"
    assert feature_key("observation.images.wrist_image") == "observation.vis_feats.wrist_image"


def test_projector_is_layernorm_then_linear() -> None:
    torch.manual_seed(0)
    proj = GraftProjector(6, 10)
    x = torch.randn(2, 5, 6)
    expected = proj.proj(nn.functional.layer_norm(x, (6,), proj.norm.weight, proj.norm.bias))
    assert proj(x).shape == (2, 5, 10)
    torch.testing.assert_close(proj(x), expected)
    # the LayerNorm makes the projector blind to a per-token affine change of the features
    torch.testing.assert_close(proj(3 * x + 1), proj(x), atol=1e-4, rtol=1e-4)
    assert (proj.in_features, proj.out_features) == (6, 10)


def test_projector_accepts_half_precision_cached_features() -> None:
    proj = GraftProjector(4, 3)
    out = proj(torch.randn(2, 7, 4).to(torch.float16))
    assert out.dtype == torch.float32 and out.shape == (2, 7, 3)


def test_pass_through_projector_feeds_tokens_unchanged() -> None:
    x = torch.randn(2, 3, 8, dtype=torch.bfloat16)
    ident = PassThroughProjector(8)
    assert torch.equal(ident(x), x.float())
    assert list(ident.parameters()) == [] and ident.out_features == 8


def test_pass_through_tower_returns_its_input_and_has_a_dtype() -> None:
    tower = PassThroughTower()
    x = torch.randn(2, 16, 5)
    assert tower(x, patch_attention_mask=None).last_hidden_state is x
    assert tower.dtype == torch.float32
    assert tower.to(torch.bfloat16).dtype == torch.bfloat16
    assert list(tower.parameters()) == [] and tower.state_dict() == {}


def test_freeze_all_but_leaves_only_the_given_module_trainable() -> None:
    model = nn.Sequential(nn.Linear(3, 4), nn.Linear(4, 2))
    extra = nn.Linear(2, 2)
    freeze_all_but(model, model[1])
    assert [p.requires_grad for p in model.parameters()] == [False, False, True, True]
    freeze_all_but(model, extra)  # a module outside the model: the model is then fully frozen
    assert not any(p.requires_grad for p in model.parameters())
    assert all(p.requires_grad for p in extra.parameters())


def test_freeze_report_counts_each_parameter_once_and_reports_the_rest() -> None:
    shared = nn.Linear(4, 4, bias=False)
    model = nn.ModuleDict({"a": nn.Sequential(shared, nn.Linear(4, 2)), "b": shared, "c": nn.Linear(2, 1)})
    freeze_all_but(model, model["c"])
    report = freeze_report({"a": model["a"], "tied": model["b"], "ab": (model["a"], model["b"])}, model)
    assert isinstance(report, FreezeReport)
    rows = {r.module: (r.params, r.trainable) for r in report.rows}
    assert rows == {"a": (16 + 10, 0), "tied": (0, 0), "ab": (0, 0), "other": (3, 3)}
    assert report.total == sum(p.numel() for p in model.parameters()) == 29
    assert report.trainable == 3
    text = str(report)
    assert "other" in text and "trainable" in text and "29" in text


def test_freeze_report_changes_name_only_the_rows_that_differ_and_the_total() -> None:
    """What a log says of a later graft of the same policy: a module made trainable, beside the first table."""
    model = nn.ModuleDict({"a": nn.Linear(4, 2), "c": nn.Linear(2, 1)})  # a: 10 params, c: 3
    freeze_all_but(model, model["c"])
    first = freeze_report({"a": model["a"], "c": model["c"]}, model)
    freeze_all_but(model, model)
    later = freeze_report({"a": model["a"], "c": model["c"]}, model)
    assert later.changes(first) == "a 10 params, 10 trainable; total 13 params, 13 trainable"
    assert first.changes(first) == "total 13 params, 3 trainable" and later != first


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_projector_gradients_flow(dtype: torch.dtype) -> None:
    proj = GraftProjector(5, 3)
    proj(torch.randn(4, 2, 5).to(dtype)).sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in proj.proj.parameters())


@pytest.mark.parametrize("bf16", [False, True])
def test_projector_gradients_do_not_depend_on_the_thread_count(bf16: bool) -> None:
    """The projector's gradients, its norm's scale and shift among them, are the same bits on one intra-op thread and
    on two (torch's fused layer norm summed those two in one partial sum per thread), so a fit's numbers do not
    depend on the cores it ran on; in fp32 they are the gradients float64 computes."""
    torch.manual_seed(0)
    proj = GraftProjector(96, 32)
    with torch.no_grad():
        proj.norm.weight.uniform_(0.5, 1.5)
        proj.norm.bias.uniform_(-0.5, 0.5)
    x = torch.randn(64, 32, 96)  # 2048 rows, as a batch of cached tokens
    grads, threads = {}, torch.get_num_threads()
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            proj.zero_grad()
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                out = proj(x)
            out.float().square().mean().backward()
            grads[n] = [p.grad.clone() for p in proj.parameters()]
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(grads[1], grads[2], strict=True))
    if not bf16:
        reference = GraftProjector(96, 32).double()
        reference.load_state_dict(proj.state_dict())
        reference(x.double()).square().mean().backward()
        for ours, exact in zip(grads[1], reference.parameters(), strict=True):
            torch.testing.assert_close(ours.double(), exact.grad, rtol=1e-4, atol=1e-7)


def test_fused_projector_gives_each_member_its_own_rows_and_gradients() -> None:
    torch.manual_seed(0)
    members = [GraftProjector(6, 4) for _ in range(3)]
    fused = FusedProjector(members)
    x = torch.randn(2 + 0 + 3, 5, 6)
    with fused.rows([2, 0, 3]):
        out = fused(x)
    torch.testing.assert_close(out, torch.cat([members[0](x[:2]), members[2](x[2:])]), rtol=0, atol=0)
    out[2:].sum().backward()  # only the third member's rows: only its parameters get a gradient
    assert all(p.grad is None or not p.grad.any() for m in members[:2] for p in m.parameters())
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in members[2].parameters())
    with pytest.raises(RuntimeError, match="needs its members' rows of a batch of 5"):
        fused(x)
    with fused.rows([1, 1, 1]), pytest.raises(RuntimeError, match=r"has \[1, 1, 1\]"):
        fused(x)
    with pytest.raises(ValueError, match="must share their widths"):
        FusedProjector([GraftProjector(6, 4), GraftProjector(8, 4)])


def test_at_width_rebuilds_only_untrained_width_tensors_and_refuses_trained_ones() -> None:
    """A zero-image projector saved at width 12 becomes one of width 5 that maps zero features to the same tokens
    (its trained bias kept, the width's tensors at their init); a projector whose width tensors trained is refused
    by name, and equal widths give the saved dict itself."""
    from graftcache.fit.controls import zero_image_projector

    trained = zero_image_projector(12, 7)
    with torch.no_grad():
        trained.proj.bias.copy_(torch.arange(7.0))
    saved = {f"model.connector.{k}": v.clone() for k, v in trained.state_dict().items()}
    saved["model.lora_A"] = torch.ones(3)  # outside the projector: kept as it is
    assert at_width(saved, zero_image_projector, 12) is saved
    narrow = at_width(saved, zero_image_projector, 5)
    assert narrow.keys() == saved.keys() and torch.equal(narrow["model.lora_A"], torch.ones(3))
    rebuilt = zero_image_projector(5, 7)
    rebuilt.load_state_dict({k.removeprefix("model.connector."): v for k, v in narrow.items() if "connector" in k})
    assert torch.equal(rebuilt(torch.zeros(2, 3, 5)), trained(torch.zeros(2, 3, 12)))
    assert torch.equal(rebuilt(torch.zeros(1, 1, 5))[0, 0], torch.arange(7.0))
    saved["model.connector.norm.bias"][4] = 0.5  # trained: the function now depends on the width
    with pytest.raises(ValueError, match=r"model\.connector\.norm\.bias trained away from its init, .*\(12\)"):
        at_width(saved, zero_image_projector, 5)
    with pytest.raises(ValueError, match="no single graft projector"):
        at_width({"model.lora_A": torch.ones(3)}, zero_image_projector, 5)
