"""The data-scale plot draws the measured points of data_scale.json."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import imageio.v3 as iio

HERE = Path(__file__).parent


def test_the_plot_is_drawn_from_the_measured_points(tmp_path, monkeypatch):
    spec = importlib.util.spec_from_file_location("plot_data_scale", HERE / "plot_data_scale.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    (tmp_path / "figures").mkdir()
    (tmp_path / "data_scale.json").write_text((HERE / "data_scale.json").read_text())
    monkeypatch.setattr(mod, "HERE", tmp_path)
    out = mod.main()
    assert out == tmp_path / "figures" / "data_scale.png"
    h, w, _ = iio.imread(out).shape
    assert w > h > 200
