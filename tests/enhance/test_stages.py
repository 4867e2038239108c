"""The enhancement chain: stages built from the config, and a cache key derived from every stage's fields."""

import dataclasses
import shutil
from typing import ClassVar

import pytest
import torch

import naka_gs_plugin.enhance.pipeline as pipeline_mod
import naka_gs_plugin.enhance.stages as stages_mod
from naka_gs_plugin.enhance.checkpoint import save_correction
from naka_gs_plugin.enhance.chroma import capture_chroma
from naka_gs_plugin.enhance.correction_net import ChromaGuided, ChromaGuidedConfig
from naka_gs_plugin.enhance.naka import naka_enhance
from naka_gs_plugin.enhance.pipeline import EnhanceConfig, Enhancer
from naka_gs_plugin.enhance.stages import (
    CaptureChromaStage,
    CaptureToneStage,
    CorrectionStage,
    ExposureStage,
    NakaStage,
    ViewStage,
)
from naka_gs_plugin.enhance.tone import capture_tone

SMALL = ChromaGuidedConfig(widths=(8, 8, 8, 8), enc_residual=(0, 0, 0))


def _images(n=2):
    g = torch.Generator().manual_seed(0)
    return [(torch.rand(24, 32, 3, generator=g) * 40).to(torch.uint8) for _ in range(n)]


def _key(**options):
    return Enhancer(EnhanceConfig(correction="none", **options)).key()


def test_the_config_builds_the_chain_in_order(tmp_path):
    ckpt = save_correction(ChromaGuided(SMALL), tmp_path / "net.pt")
    enhancer = Enhancer(EnhanceConfig(correction=str(ckpt), correction_mode="exact"))
    assert [type(s) for s in enhancer.view_stages] == [NakaStage, CorrectionStage, CaptureChromaStage, CaptureToneStage]
    assert [type(s) for s in enhancer.scene_stages] == [ExposureStage]
    plain = Enhancer(EnhanceConfig(correction="none", tone="network"))
    assert [type(s) for s in plain.view_stages] == [NakaStage, CaptureChromaStage]
    assert Enhancer(EnhanceConfig(exposure="none")).scene_stages == []
    assert Enhancer(EnhanceConfig(method="none")).view_stages == []


def test_a_new_stage_is_one_class_plus_one_config_field(monkeypatch):
    """A stage added to the chain runs in its place and its option enters the cache key with no other edit."""

    @dataclasses.dataclass
    class Tint(ViewStage):
        name: ClassVar[str] = "tint"
        gain: float = 1.0

        @classmethod
        def build(cls, config, enhancer):
            return cls(gain=config.tint)

        def apply(self, image, low):
            return (image * self.gain).clamp(0, 1)

    @dataclasses.dataclass
    class TintConfig(EnhanceConfig):
        tint: float = 1.0

    monkeypatch.setattr(stages_mod, "CHAIN", (*stages_mod.CHAIN, Tint))
    monkeypatch.setattr(pipeline_mod, "CHAIN", stages_mod.CHAIN)

    def run(tint):
        enhancer = Enhancer(TintConfig(correction="none", exposure="none", tone="capture", use_cache=False, tint=tint))
        return enhancer, enhancer.enhance_images(_images())

    plain, darker = run(1.0), run(0.5)
    assert [s.name for s in plain[0].view_stages] == ["naka", "chroma", "tone", "tint"]
    assert plain[0]._keys(_images()) != darker[0]._keys(_images())
    for a, b in zip(plain[1], darker[1]):
        torch.testing.assert_close(b, (a * 0.5).clamp(0, 1), atol=2e-5, rtol=0)


@pytest.mark.parametrize(
    "option, value",
    [("sigma", 0.07), ("sigma", "auto"), ("n", 0.8), ("chroma_blur", 5.0), ("tone", "network")],
)
def test_every_option_that_changes_the_cached_views_changes_the_key(option, value):
    assert _key(**{option: value}) != _key()


@pytest.mark.parametrize("option, value", [("exposure", 0.3), ("exposure", "none"), ("use_cache", False)])
def test_options_applied_after_the_cache_leave_the_key_alone(option, value):
    assert _key(**{option: value}) == _key()


def test_a_stage_whose_maths_changed_without_a_field_change_is_keyed_anew(monkeypatch):
    before = _key(tone="capture")
    monkeypatch.setattr(CaptureToneStage, "version", CaptureToneStage.version + 1)
    assert _key(tone="capture") != before


def test_correction_is_keyed_by_weights_content_and_mode_not_path(tmp_path):
    ckpt = save_correction(ChromaGuided(SMALL), tmp_path / "net.pt")
    copy = tmp_path / "elsewhere" / "net.pt"
    copy.parent.mkdir()
    shutil.copyfile(ckpt, copy)
    a = CorrectionStage.from_file(ckpt, "exact", torch.device("cpu"))
    b = CorrectionStage.from_file(copy, "exact", torch.device("cpu"))
    assert a.key() == b.key() and "path" not in a.key() and "device" not in a.key()
    assert a.key() != CorrectionStage.from_file(ckpt, "lean-f32", torch.device("cpu")).key()


def test_the_chain_composes_naka_capture_chroma_and_capture_tone():
    images = _images()
    out = Enhancer(EnhanceConfig(correction="none", exposure="none", tone="capture", use_cache=False)).enhance_images(
        images
    )
    for got, image in zip(out, images):
        low = image.float() / 255
        torch.testing.assert_close(got, capture_tone(capture_chroma(naka_enhance(low), low), low), atol=1e-4, rtol=0)


def test_stages_report_their_own_time():
    enhancer = Enhancer(EnhanceConfig(correction="none", use_cache=False))
    enhancer.enhance_images(_images())
    assert enhancer.last_run["naka_seconds"] > 0 and enhancer.last_run["chroma_seconds"] > 0
