"""A self-contained Meshcat recording of a multibody run, as one HTML file.

The model is parsed next to a ``SceneGraph``, a ``MeshcatVisualizer`` records
its poses at the logged positions ``q(t)``, and ``Meshcat.StaticHtml()`` exports
the recording with the viewer, so the file opens in a browser without a server.
Nothing is simulated again: the poses are the run's own logs.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from ofrl_drake.errors import ModelError, one_line

__all__ = [
    "FRAMES_PER_SECOND",
    "MeshcatUnavailable",
    "animation_html",
    "camera_window",
    "frame_samples",
]

#: Frame rate of the recording; denser logs are thinned to it.
FRAMES_PER_SECOND = 64.0


class MeshcatUnavailable(RuntimeError):
    """Meshcat could not start (e.g. no free port); the run goes on without a recording."""


def frame_samples(t: np.ndarray) -> np.ndarray:
    """Indices of the samples kept: at least one frame period apart, the last always."""
    keep, last = [], -np.inf
    for i, ti in enumerate(t):
        if ti - last >= 1.0 / FRAMES_PER_SECOND - 1e-12:
            keep.append(i)
            last = ti
    if keep[-1] != len(t) - 1:
        keep.append(len(t) - 1)
    return np.asarray(keep)


def animation_html(model: str | Path, t: np.ndarray, q: np.ndarray) -> str | None:
    """HTML of ``model`` moving through the positions ``q(t)``.

    Parameters
    ----------
    model : str or Path
        A model file or ``package://`` URL, parsed as in
        :meth:`~ofrl_drake.model.ControlAffineSystem.from_multibody`.
    t : ndarray, shape (T,)
        Sample times [s], increasing.
    q : ndarray, shape (T, nq)
        Generalized positions of the plant at those times (the plant's own
        coordinates, not shifted by an equilibrium).

    Returns
    -------
    str or None
        The page, or None when the model has no illustration geometry.

    Raises
    ------
    MeshcatUnavailable
        If Meshcat cannot start.
    ModelError
        If ``q`` does not have one column per position of the model, or ``t``
        not one time per row of ``q``.
    """
    from pydrake.geometry import GeometrySet, Meshcat, MeshcatVisualizer, Role
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=0.0)
    text = str(model)
    if "://" in text:
        Parser(plant).AddModels(url=text)  # type: ignore[call-arg]  # pydrake stub lacks url=
    else:
        Parser(plant).AddModels(file_name=Path(text))
    plant.Finalize()
    if scene_graph.model_inspector().NumGeometriesWithRole(Role.kIllustration) == 0:
        return None
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != plant.num_positions() or q.shape[0] == 0:
        raise ModelError(
            f"q must have shape (T, {plant.num_positions()}), T >= 1, for {text}; got "
            f"{q.shape}. Pass one row per time and one column per position of the model "
            f"(the first {plant.num_positions()} states, in the plant's own coordinates)."
        )
    t = np.asarray(t, dtype=float)
    if t.shape != (q.shape[0],):
        raise ModelError(
            f"t must have shape (T,) = ({q.shape[0]},), one time per row of q; got "
            f"{t.shape}. Pass the run's sample times with its positions."
        )
    logger = logging.getLogger("drake")  # Drake's C++ log follows this logger's level
    previous = logger.level
    logger.setLevel(logging.WARNING)  # no "Meshcat listening ..." line on the console
    try:
        meshcat = Meshcat()
    except Exception as err:
        raise MeshcatUnavailable(one_line(err)) from None
    finally:
        logger.setLevel(previous)
    visualizer = MeshcatVisualizer.AddToBuilder(builder, scene_graph, meshcat)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyContextFromRoot(context)
    visualizer_context = visualizer.GetMyContextFromRoot(context)
    scene_context = scene_graph.GetMyContextFromRoot(context)
    inspector = scene_graph.model_inspector()
    geometries = inspector.GetGeometryIds(
        GeometrySet(inspector.GetAllFrameIds()), Role.kIllustration
    )
    sizes = np.array([_radius(inspector.GetShape(g)) for g in geometries])
    centres = []
    visualizer.StartRecording(set_transforms_while_recording=False)
    for i in frame_samples(t):
        context.SetTime(float(t[i]))
        plant.SetPositions(plant_context, q[i])
        visualizer.ForcedPublish(visualizer_context)
        query = scene_graph.get_query_output_port().Eval(scene_context)
        centres.append([query.GetPoseInWorld(g).translation() for g in geometries])
    visualizer.StopRecording()
    visualizer.PublishRecording()
    _frame_camera(meshcat, np.asarray(centres), sizes)
    return meshcat.StaticHtml()


#: Margin around the swept volume of the model, as a fraction of its size.
CAMERA_MARGIN = 0.15
#: Widest aspect (width / height) of a planar view; a tall view is widened to it.
ASPECT = 16.0 / 9.0


def _radius(shape: Any) -> float:
    """Radius of a sphere around ``shape`` centred on its frame (0 for unknown shapes)."""
    from pydrake.geometry import Box, Capsule, Cylinder, Ellipsoid, Sphere

    if isinstance(shape, Sphere):
        return shape.radius()
    if isinstance(shape, Box):
        return 0.5 * float(np.linalg.norm([shape.width(), shape.depth(), shape.height()]))
    if isinstance(shape, Cylinder):
        return float(np.hypot(shape.radius(), 0.5 * shape.length()))
    if isinstance(shape, Capsule):
        return shape.radius() + 0.5 * shape.length()
    if isinstance(shape, Ellipsoid):
        return max(shape.a(), shape.b(), shape.c())
    return 0.0


def camera_window(centres: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The box ``(lower, upper)`` in world coordinates that the model sweeps during the run.

    ``centres`` has shape (frames, geometries, 3): each geometry's origin per
    frame; ``sizes`` the radius of a sphere around each geometry. The box is
    widened by :data:`CAMERA_MARGIN` of its largest side.
    """
    lower = (centres - sizes[None, :, None]).min(axis=(0, 1))
    upper = (centres + sizes[None, :, None]).max(axis=(0, 1))
    pad = CAMERA_MARGIN * max(float(np.max(upper - lower)), 1e-3)
    return lower - pad, upper + pad


def _frame_camera(meshcat: Any, centres: np.ndarray, sizes: np.ndarray) -> None:
    """Point Meshcat's camera at the model: a 2D view for a model moving in the x-z plane.

    Planar models (the cart-pole, the acrobot) are drawn by an orthographic
    camera looking along +y at the window the model sweeps, so that a small
    tilt is visible; other models by a perspective camera at a distance that
    fits the swept volume.
    """
    from pydrake.math import RigidTransform

    if centres.size == 0:
        return
    lower, upper = camera_window(centres, sizes)
    centre = 0.5 * (lower + upper)
    spread_y = float(np.ptp(centres[..., 1], axis=0).max())
    if spread_y <= 1e-9:  # every geometry keeps its y: the motion is in the x-z plane
        half_w, half_h = 0.5 * (upper[0] - lower[0]), 0.5 * (upper[2] - lower[2])
        half_w = max(half_w, ASPECT * half_h)
        half_h = max(half_h, half_w / ASPECT)
        meshcat.Set2dRenderMode(
            X_WC=RigidTransform([0.0, lower[1] - 1.0, 0.0]),  # type: ignore[call-overload]  # pydrake array stub
            xmin=centre[0] - half_w,
            xmax=centre[0] + half_w,
            ymin=centre[2] - half_h,
            ymax=centre[2] + half_h,
        )
        return
    radius = 0.5 * float(np.linalg.norm(upper - lower))
    distance = radius / np.tan(np.radians(75.0) / 2)  # Meshcat's default field of view
    direction = np.array([1.0, -2.0, 1.0]) / np.sqrt(6.0)
    meshcat.SetCameraPose(centre + distance * direction, centre)
