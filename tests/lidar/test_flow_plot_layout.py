"""The matplotlib bird's-eye view (``floxels show``, the demo, the KITTI pictures; issue 45):
the colour wheel and the object key sit outside the scene, and the objects' labels do not
overlap one another, also with objects crowded together."""

import numpy as np
import pytest

pytest.importorskip("matplotlib")


def _crowded_scene(seed=0):
    rng = np.random.default_rng(seed)
    static = np.c_[rng.uniform(-40, 40, (20000, 2)), rng.uniform(-1, 1, 20000)]
    parts, flows = [static], [np.zeros_like(static)]
    # nine small moving objects, most of them packed around the sensor (as in the KITTI sweep)
    centres = [(-20, 0), (-15, 2), (-10, -1), (-20, -5), (10, 0), (15, 2), (20, -1), (30, 35), (-35, -30)]
    for k, (cx, cy) in enumerate(centres):
        p = np.c_[rng.uniform(-1, 1, (300, 2)) + [cx, cy], rng.uniform(-1, 1, 300)]
        parts.append(p)
        flows.append(np.tile([0.2 + 0.05 * k, 0.1 * (k % 3 - 1), 0.0], (300, 1)))
    return np.concatenate(parts), np.concatenate(flows)


def _px(artist, renderer):
    e = artist.get_window_extent(renderer)
    return e.x0, e.y0, e.x1, e.y1


def _overlap(a, b) -> float:
    return max(0.0, min(a[2], b[2]) - max(a[0], b[0])) * max(0.0, min(a[3], b[3]) - max(a[1], b[1]))


@pytest.mark.parametrize("with_truth", [False, True])
def test_wheel_outside_the_scene_and_labels_apart(with_truth):
    import matplotlib.pyplot as plt

    from floxels_ext.lidar.viz.flow_plot import flow_figure

    pts, flow = _crowded_scene()
    fig = flow_figure(pts, flow, gt_flow=flow if with_truth else None, frame_period=0.1,
                      view=((-40, 40), (-40, 40)))
    try:
        fig.canvas.draw()
        r = fig.canvas.get_renderer()
        axes = {a.get_label(): a for a in fig.axes}
        scenes = [axes[k] for k in ("scene", "truth") if k in axes]
        for key in ("wheel", "key"):  # outside every scene panel
            for sc in scenes:
                assert _overlap(_px(axes[key], r), _px(sc, r)) == 0, key
        for sc in scenes:
            labels = [_px(t, r) for t in sc.texts]
            assert len(labels) == 9
            for i in range(len(labels)):
                for j in range(i):
                    assert _overlap(labels[i], labels[j]) == 0, (i, j)
        key_text = axes["key"].texts[0].get_text()
        assert "1: " in key_text and "9: " in key_text and "m/s" in key_text
        assert ("(true " in key_text) == with_truth
    finally:
        plt.close(fig)


def test_plain_raster_wheel_in_a_strip_beside_the_view():
    from floxels_ext.lidar.viz.show import render_frame

    pts, flow = _crowded_scene()
    data = {"points": pts, "flow": flow, "mask": np.ones(len(pts), bool)}
    bare = render_frame(data, legend=False)
    img = render_frame(data)
    assert img.shape[1] == bare.shape[1] + 72
    np.testing.assert_array_equal(img[:, :bare.shape[1]], bare)  # the view untouched by the wheel
    assert (img[:, bare.shape[1]:] != img[0, -1]).any()  # the wheel is drawn in the strip
