"""Readable figures (issue 15): the map slice has the map's aspect ratio, trajectory ellipses
can be switched off and the legend names the run."""
from __future__ import annotations

import numpy as np
import pytest

from mapping import OcTree
from mapping.export import save_height_slice


def _png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def test_slice_of_a_long_corridor_is_a_wide_figure_not_a_strip(tmp_path):
    rng = np.random.default_rng(0)
    walls = np.concatenate([np.c_[rng.uniform(0, 20, 4000), np.full(4000, side),
                                  rng.uniform(0, 2, 4000)] for side in (-1.0, 1.0)])
    tree = OcTree(0.1)
    tree.insert_point_cloud(walls, np.array([0.5, 0.0, 1.0]))
    save_height_slice(tree, tmp_path / "slice.png", height=1.0)
    width, height = _png_size(tmp_path / "slice.png")
    assert width / height > 3.0  # 20 m x 2 m: a 4:3 canvas gave mostly blank space


@pytest.mark.parametrize("ellipses", [True, False])
def test_trajectory_figure_ellipses_switch_and_name_in_legend(ellipses, monkeypatch, tmp_path):
    import pipelines.plotting as plotting
    from pipelines.vpslam import VpSlamResult, plot_trajectory

    captured = {}
    monkeypatch.setattr(plotting, "save_figure", lambda fig, path: captured.update(fig=fig))
    n = 30
    p = np.c_[np.linspace(0, 5, n), np.zeros(n), np.ones(n)]
    result = VpSlamResult(graph=None, tree=None, report={"vp_model": "manhattan",
                                                         "name": "run_vp"},
                          timestamps=np.arange(n) * 0.3, positions=p,
                          position_covs=np.tile(np.eye(3) * 1e-3, (n, 1, 1)),
                          T_world_camera=np.tile(np.eye(4), (n, 1, 1)), positions_gt=p + 0.01)
    plot_trajectory(result, tmp_path / "t.png", ellipses=ellipses)
    top = captured["fig"].axes[0]
    labels = [t.get_text() for t in top.get_legend().get_texts()]
    assert "run_vp" in labels and "ground truth" in labels
    n_lines = len(top.get_lines())
    assert (n_lines > 2 + n // 2) if ellipses else (n_lines == 2)
    if ellipses:  # thin and under the trajectory
        ellipse = [ln for ln in top.get_lines() if ln.get_color() == "r"][0]
        assert ellipse.get_linewidth() <= 0.3 and ellipse.get_zorder() < 3
