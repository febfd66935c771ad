"""animation.html: a Meshcat recording of a multibody model, exported whole."""

import base64
import re
from types import SimpleNamespace

import msgpack
import numpy as np
import pytest

from ofrl_drake.animation import (
    FRAMES_PER_SECOND,
    MeshcatUnavailable,
    animation_html,
    camera_window,
    frame_samples,
)
from ofrl_drake.errors import ModelError

CART_POLE_SDF = "package://drake/examples/multibody/cart_pole/cart_pole.sdf"


def set_animation(html):
    """The ``set_animation`` command embedded in a Meshcat StaticHtml page."""
    for blob in re.findall(r'data:application/octet-binary;base64,([A-Za-z0-9+/=]+)"', html):
        command = msgpack.unpackb(base64.b64decode(blob), strict_map_key=False)
        if command.get("type") == "set_animation":
            return command
    raise AssertionError("no recording in the page")


def test_the_page_holds_the_recording_of_the_given_positions():
    t = np.arange(0.0, 2.0 + 1e-9, 0.01)  # denser than the frame rate: thinned
    q = np.stack([0.5 * np.sin(t), np.pi + 0.3 * np.cos(3 * t)], axis=1)
    html = animation_html(CART_POLE_SDF, t, q)
    assert html.lstrip().lower().startswith("<!doctype html>")
    assert "ws://" not in html.split("<script", 1)[0]  # no server needed to open it
    animation = set_animation(html)
    clips = {a["path"].rsplit("/", 1)[-1]: a["clip"] for a in animation["animations"]}
    assert set(clips) == {"Cart", "Pole"}
    kept = frame_samples(t)
    assert np.all(np.diff(t[kept]) >= 1 / FRAMES_PER_SECOND - 1e-12)
    assert kept[0] == 0 and kept[-1] == t.size - 1
    cart = next(k for k in clips["Cart"]["tracks"] if k["name"] == ".position")
    assert len(cart["keys"]) == kept.size
    positions = np.array([k["value"][0] for k in cart["keys"]])
    np.testing.assert_allclose(positions, q[kept, 0], rtol=0, atol=1e-12)
    frames = np.array([k["time"] for k in cart["keys"]])
    # Meshcat keys whole frames: each time to within one frame.
    np.testing.assert_allclose(frames / clips["Cart"]["fps"], t[kept], atol=1 / FRAMES_PER_SECOND)


@pytest.mark.parametrize(
    ("t", "q", "match"),
    [
        ([0.0], np.zeros((1, 4)), r"q must have shape \(T, 2\), T >= 1, for .*; got \(1, 4\)"),
        ([], np.zeros((0, 2)), r"q must have shape \(T, 2\), T >= 1, for .*; got \(0, 2\)"),
        ([0.0, 0.1], np.zeros((3, 2)), r"t must have shape \(T,\) = \(3,\), one time per row"),
        ([[0.0, 0.1]], np.zeros((2, 2)), r"t must have shape \(T,\) = \(2,\).*got \(1, 2\)"),
    ],
)
def test_positions_and_times_of_the_wrong_size_are_refused(t, q, match):
    # Before: a bare ValueError for q, and an IndexError from deep inside for t.
    with pytest.raises(ModelError, match=match):
        animation_html(CART_POLE_SDF, np.asarray(t), q)


def test_a_model_without_geometry_has_no_animation(tmp_path):
    model = tmp_path / "slider.sdf"
    model.write_text(
        """<?xml version="1.0"?>
<sdf version="1.7"><model name="slider">
  <link name="block"><inertial><mass>1.0</mass></inertial></link>
  <joint name="slide" type="prismatic"><parent>world</parent><child>block</child>
    <axis><xyz>1 0 0</xyz></axis></joint>
</model></sdf>
"""
    )
    assert animation_html(model, np.array([0.0, 1.0]), np.zeros((2, 1))) is None


def test_meshcat_that_cannot_start_is_reported(monkeypatch):
    import pydrake.geometry

    def no_port(*args, **kwargs):
        raise RuntimeError("Meshcat failed to open a websocket port.")

    monkeypatch.setattr(pydrake.geometry, "Meshcat", no_port)
    with pytest.raises(MeshcatUnavailable, match="failed to open a websocket port"):
        animation_html(CART_POLE_SDF, np.array([0.0]), np.array([[0.0, np.pi]]))


def test_cli_notes_a_missing_meshcat_in_one_line_and_goes_on(monkeypatch, tmp_path):
    from ofrl_drake import cli

    def unavailable(*args):
        raise MeshcatUnavailable("no free port")

    monkeypatch.setattr("ofrl_drake.animation.animation_html", unavailable)

    class Result:
        t = np.array([0.0])

        @staticmethod
        def original(key):
            return np.zeros((1, 4))

    scenario = SimpleNamespace(plant=SimpleNamespace(multibody=CART_POLE_SDF))
    note = cli._write_animation(scenario, Result(), tmp_path)
    assert note == "note: Meshcat cannot start (no free port); no animation.html written."
    assert not (tmp_path / "animation.html").exists()


def camera(html):
    """The orthographic camera window (left, right, bottom, top) set in the page, or None."""
    for blob in re.findall(r'data:application/octet-binary;base64,([A-Za-z0-9+/=]+)"', html):
        command = msgpack.unpackb(base64.b64decode(blob), strict_map_key=False)
        if command.get("path") == "/Cameras/default/rotated" and command["type"] == "set_object":
            cam = command["object"]["object"]
            if cam["type"] == "OrthographicCamera":
                return cam["left"], cam["right"], cam["bottom"], cam["top"]
    return None


def test_the_camera_frames_a_planar_model_tightly_so_a_small_tilt_shows():
    # The cart-pole balancing: cart within 0.1 m, pole 0.15 rad from upright (pi).
    t = np.arange(0.0, 2.0, 0.01)
    q = np.stack([0.1 * np.sin(t), np.pi + 0.15 * np.cos(3 * t)], axis=1)
    left, right, bottom, top = camera(animation_html(CART_POLE_SDF, t, q))
    # The window holds the pole's tip (0.5 m above the cart) at every tilt and the cart at
    # every position ...
    tip_x = 0.1 * np.sin(t) + 0.5 * np.sin(0.15 * np.cos(3 * t))
    assert left < tip_x.min() and tip_x.max() < right
    assert bottom < 0.0 and 0.5 * np.cos(0.15) < top
    # ... and is tight: the 0.5 m pole spans more than a third of its height, and the
    # window is no wider than the 16:9 frame around that height.
    assert 0.5 / (top - bottom) > 1 / 3
    assert (right - left) / (top - bottom) <= 16 / 9 + 1e-9


def test_camera_window_holds_every_geometry_with_a_margin():
    rng = np.random.default_rng(0)
    centres = rng.normal(size=(20, 3, 3))
    sizes = np.array([0.1, 0.0, 0.5])
    lower, upper = camera_window(centres, sizes)
    assert np.all(lower < (centres - sizes[None, :, None]).min(axis=(0, 1)))
    assert np.all(upper > (centres + sizes[None, :, None]).max(axis=(0, 1)))
    tight = (centres + sizes[None, :, None]).max(axis=(0, 1)) - (
        centres - sizes[None, :, None]
    ).min(axis=(0, 1))
    np.testing.assert_allclose(upper - lower, tight + 2 * 0.15 * tight.max(), rtol=1e-12)
