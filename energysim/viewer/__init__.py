"""A live browser viewer for trajectories (three.js shipped inside the package; no network needed).

    viewer = Viewer(scene); viewer.serve(8080); viewer.loop_states(states); viewer.stop()

`Viewer` takes only the mesh and plain state tensors; `strain_energy_density` is a helper that computes
a colouring from a scene's elasticity terms. `ServerLimits` sets the server's timeouts and limits.
"""

from .httpd import ServerLimits
from .scalars import strain_energy_density
from .server import Viewer

__all__ = ["ServerLimits", "Viewer", "strain_energy_density"]
