"""Learning methods: HAPPO, HAPPO+CBF, TALO+CBF, SAIL+CBF and SAGE (Sec. III)."""
from common.algos.config import AlgoConfig

__all__ = ["AlgoConfig"]
