"""The exact joint CBF-QP shield (Eq. qpshield): the solver front end
(``qp``), the numba dual active-set QP solver (``qp_solver``), the OSQP backend and random
problem families for tests and benchmarks."""
