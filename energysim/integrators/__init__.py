"""How a state advances: one step (`step`: implicit Euler, TR-BDF2, leapfrog, quasi-static equilibrium),
the explicit leapfrog and its contact (`explicit`), the differentiable step's adjoint (`adjoint`) and
many steps at once (`rollout`)."""
