"""The step objective and its derivatives: `Objective` (the sum of a step's terms over the free DOFs and
the one convergence measure), every derivative the solvers take (`derivatives`), and the same
evaluations compiled by `torch.compile` (`compiled`)."""
