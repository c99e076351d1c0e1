"""Linear algebra of the solvers: Hessian assembly into CSR, LAPACK band and block-tridiagonal Cholesky
of per-body Hessians in breadth-first level order, fused products of tiny per-element matrices, and the
caches of sparsity patterns and layouts they share."""
