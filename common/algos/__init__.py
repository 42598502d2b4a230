"""Learning methods: HAPPO, HAPPO+CBF, TALO+CBF, SAIL+CBF and SAGE (Sec. III).

``AlgoConfig`` and ``METHODS`` (the registry) are importable without torch;
``make_method``/``Method`` load the torch learner on first access.
"""
from common.algos.config import AlgoConfig
from common.algos.registry import METHODS

__all__ = ["AlgoConfig", "METHODS", "Method", "make_method"]


def __getattr__(name: str):
    if name in ("Method", "make_method"):
        from common.algos import methods

        return getattr(methods, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
