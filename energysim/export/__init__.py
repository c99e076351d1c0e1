"""Export of simulation results: VTK frames, ``.pvd`` and XDMF time series, PNG pictures, GIF/MP4 animations.

Nothing here imports the solver: `write_vtu`, `VTKSeries` and the render functions take plain arrays
(torch tensors or numpy arrays); `export_rollout` reads a scene's terms to name what its states mean
(strain energy, activations), but never steps it. pyvista is imported only when a render function is
called.
"""

from .render import render_gif, render_mp4, render_png
from .rollout_vtk import element_activation, export_rollout, vertex_spring_activation
from .series import VTKSeries
from .vtk import write_pvd, write_vtu

__all__ = [
    "VTKSeries",
    "element_activation",
    "export_rollout",
    "render_gif",
    "render_mp4",
    "render_png",
    "vertex_spring_activation",
    "write_pvd",
    "write_vtu",
]
