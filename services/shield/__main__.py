"""python -m services.shield --config RUN.json"""
import sys

from services.base import run_entry
from services.shield.service import ShieldService

if __name__ == "__main__":
    sys.exit(run_entry("shield", ShieldService))
