"""A benchmark whose peer (Mitsuba variant) is missing fails with a message, never switches."""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def tte():
    with pytest.MonkeyPatch.context() as mp:
        mp.syspath_prepend(str(REPO / "benchmarks"))
        spec = importlib.util.spec_from_file_location(
            "trace_time_error", REPO / "benchmarks" / "trace_time_error.py"
        )
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    return mod


def fake_mitsuba(loadable: set[str]) -> types.ModuleType:
    """A stand-in for the mitsuba module: offers llvm_ad_rgb and scalar_rgb, loads only some."""
    mi = types.ModuleType("mitsuba")
    state = {"variant": None}

    def set_variant(name: str) -> None:
        if name not in loadable:
            raise ImportError(f"libLLVM not found while loading {name}")
        state["variant"] = name

    mi.variants = lambda: ["scalar_rgb", "llvm_ad_rgb"]
    mi.set_variant = set_variant
    mi.variant = lambda: state["variant"]
    return mi


def test_unloadable_llvm_variant_fails_and_names_the_fix(tte, monkeypatch):
    monkeypatch.setitem(sys.modules, "mitsuba", fake_mitsuba({"scalar_rgb"}))
    with pytest.raises(tte.PeerMissingError, match=r"'llvm_ad_rgb'.*make bench-deps"):
        tte.load_mitsuba("llvm_ad_rgb")
    assert sys.modules["mitsuba"].variant() is None  # nothing was switched to scalar_rgb


def test_variant_not_in_build_lists_the_available_ones(tte, monkeypatch):
    monkeypatch.setitem(sys.modules, "mitsuba", fake_mitsuba({"scalar_rgb"}))
    with pytest.raises(tte.PeerMissingError, match=r"'cuda_ad_rgb'.*scalar_rgb, llvm_ad_rgb"):
        tte.load_mitsuba("cuda_ad_rgb")


def test_explicit_variant_is_used(tte, monkeypatch):
    monkeypatch.setitem(sys.modules, "mitsuba", fake_mitsuba({"scalar_rgb", "llvm_ad_rgb"}))
    assert tte.load_mitsuba("scalar_rgb").variant() == "scalar_rgb"
    assert tte.load_mitsuba("llvm_ad_rgb").variant() == "llvm_ad_rgb"


def test_missing_mitsuba_names_make_bench_deps(tte, monkeypatch):
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # import mitsuba -> ImportError
    with pytest.raises(tte.PeerMissingError, match="make bench-deps"):
        tte.load_mitsuba("llvm_ad_rgb")
