"""Export of simulation results: VTK frames and ``.pvd`` time series, PNG pictures, GIF/MP4 animations.

Nothing here imports the solver: every function takes plain arrays (torch tensors or numpy arrays).
pyvista is imported only when a render function is called.
"""

from .render import render_gif, render_mp4, render_png
from .vtk import VTKSeries, write_pvd, write_vtu

__all__ = ["VTKSeries", "render_gif", "render_mp4", "render_png", "write_pvd", "write_vtu"]
