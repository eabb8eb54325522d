"""The deformed surface in 3-D: an oblique view, and a side view cut through the contact."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hapticrom.report.figures import Png, new_figure, render


@dataclass(frozen=True)
class View:
    """A camera for the deformed surface; ``cutaway`` removes the half nearer the camera
    through the contact point, so the cut edge shows the dent's profile."""

    name: str
    label: str
    elevation: float  # degrees
    azimuth: float  # degrees
    cutaway: bool = False
    height: float = 6.4  # inches (7.5 wide): a view along a flat organ needs less
    # The 3-D axes in figure fractions. They draw their box to fit the shorter side, so a
    # short figure gets axes taller than itself (their empty top and bottom are cut off).
    axes: tuple[float, float, float, float] = (0.0, 0.15, 1.0, 0.8)


VIEWS = (
    View("deformed-oblique", "oblique view", 35, -60),
    View(
        "deformed-side",
        "side view, cut through the contact point",
        elevation=8,
        azimuth=-90,
        cutaway=True,
        height=4.4,
        axes=(0.0, -0.28, 1.0, 1.7),
    ),
)


def far_half(vertices: np.ndarray, triangles: np.ndarray, point, azimuth: float) -> np.ndarray:
    """The triangles beyond the vertical plane through ``point`` facing a camera at ``azimuth``."""
    towards_camera = np.array([np.cos(np.radians(azimuth)), np.sin(np.radians(azimuth)), 0.0])
    centroids = vertices[triangles].mean(axis=1)
    return triangles[(centroids - point) @ towards_camera <= 0]


def surface_figure(model, displacement, factor, force, sample, view: View) -> Png:
    """The surface displaced by ``factor`` x ``displacement`` (mm), coloured by |u| (true
    mm), as seen from ``view``; the title gives the depth, the sample and the force (N)."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    magnitude = np.linalg.norm(displacement, axis=1)
    triangles = model.triangles
    if view.cutaway:
        triangles = far_half(model.vertices, triangles, model.sample_points[sample], view.azimuth)
    norm = Normalize(0.0, magnitude.max() or 1.0)
    cmap = colormaps["viridis"]
    fig = new_figure(7.5, view.height, layout=None)
    ax = fig.add_axes(view.axes, projection="3d")
    colours = cmap(norm(magnitude[triangles].mean(axis=1)))
    _draw_faces(ax, model.vertices + factor * displacement, triangles, colours, view)
    scale = "true scale" if factor == 1 else f"displacement magnified x{factor:g}"
    fig.suptitle(
        f"{view.label}\nindentation {model.trained_depth:.3g} mm at sample {sample}, "
        f"F = {force:.4g} N ({scale})",
        fontsize=10,
    )
    bar = fig.add_axes((0.25, 0.55 / view.height, 0.5, 0.15 / view.height))  # fixed inches
    fig.colorbar(
        ScalarMappable(norm=norm, cmap=cmap),
        cax=bar,
        orientation="horizontal",
        label="displacement magnitude |u| (mm, true scale)",
    )
    return render(fig, f"{view.name}.png", f"deformed surface, {view.label}")


def _draw_faces(ax, positions: np.ndarray, triangles: np.ndarray, colours, view: View) -> None:
    """The shaded triangles on 3-D axes at equal scale, seen from ``view``."""
    from matplotlib.colors import LightSource
    from matplotlib.ticker import MaxNLocator
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    faces = Poly3DCollection(
        positions[triangles],
        facecolors=colours,
        edgecolors=colours,  # thin edges of the face's own colour: no hairline gaps
        linewidths=0.2,
        shade=True,  # light and shade show the shape; colour alone would flatten it
        lightsource=LightSource(azdeg=315, altdeg=50),
    )
    ax.add_collection3d(faces)
    _fit_axes(ax, positions)
    ax.view_init(elev=view.elevation, azim=view.azimuth)
    ax.set(xlabel="x (mm)", ylabel="y (mm)", zlabel="z (mm)")
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.labelpad = 10  # clear of the tick labels, whatever the view
        axis.set_major_locator(MaxNLocator(5))  # a thin organ's axis would crowd its ticks
    if view.cutaway:  # the axis along the line of sight is seen edge-on: its ticks overlap
        ax.set(yticks=[], ylabel="")


def _fit_axes(ax, positions: np.ndarray) -> None:
    """Limits around the points with equal scale on every axis (mm look like mm)."""
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    span = np.maximum(hi - lo, 0.05 * (hi - lo).max())  # a flat organ keeps a visible depth
    ax.set(
        xlim=(lo[0], lo[0] + span[0]), ylim=(lo[1], lo[1] + span[1]), zlim=(lo[2], lo[2] + span[2])
    )
    ax.set_box_aspect(span, zoom=1.1)
