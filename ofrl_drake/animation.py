"""A self-contained Meshcat recording of a multibody run, as one HTML file.

The model is parsed next to a ``SceneGraph``, a ``MeshcatVisualizer`` records
its poses at the logged positions ``q(t)``, and ``Meshcat.StaticHtml()`` exports
the recording with the viewer, so the file opens in a browser without a server.
Nothing is simulated again: the poses are the run's own logs.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

__all__ = ["FRAMES_PER_SECOND", "MeshcatUnavailable", "animation_html", "frame_samples"]

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
    ValueError
        If ``q`` does not have one column per position of the model.
    """
    from pydrake.geometry import Meshcat, MeshcatVisualizer, Role
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    builder = DiagramBuilder()
    plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=0.0)
    text = str(model)
    if "://" in text:
        Parser(plant).AddModels(url=text)
    else:
        Parser(plant).AddModels(file_name=text)
    plant.Finalize()
    if scene_graph.model_inspector().NumGeometriesWithRole(Role.kIllustration) == 0:
        return None
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or q.shape[1] != plant.num_positions():
        raise ValueError(
            f"q must have shape (T, {plant.num_positions()}) for {text}; got {q.shape}."
        )
    logger = logging.getLogger("drake")  # Drake's C++ log follows this logger's level
    previous = logger.level
    logger.setLevel(logging.WARNING)  # no "Meshcat listening ..." line on the console
    try:
        meshcat = Meshcat()
    except Exception as err:
        raise MeshcatUnavailable(" ".join(str(err).split())) from None
    finally:
        logger.setLevel(previous)
    visualizer = MeshcatVisualizer.AddToBuilder(builder, scene_graph, meshcat)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyContextFromRoot(context)
    visualizer_context = visualizer.GetMyContextFromRoot(context)
    visualizer.StartRecording(set_transforms_while_recording=False)
    for i in frame_samples(np.asarray(t, dtype=float)):
        context.SetTime(float(t[i]))
        plant.SetPositions(plant_context, q[i])
        visualizer.ForcedPublish(visualizer_context)
    visualizer.StopRecording()
    visualizer.PublishRecording()
    return meshcat.StaticHtml()
