"""The static model of a simulation: `Scene` (mesh, masses, terms, pinned vertices, time step, solver,
integrator) and the converted copies a step runs on for another dtype or device."""
