"""The application layer: the ``sage`` command line and the experiments
(suite, report, deployment evaluation, benchmarks). It sits on top of
``deploy/``, ``services/`` and ``common/`` and nothing imports it back
(docs/architecture.md)."""
