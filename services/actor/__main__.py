"""python -m services.actor --config RUN.json --actor-id I"""
import sys

from services.actor.service import ActorService
from services.base import run_entry

if __name__ == "__main__":
    sys.exit(run_entry("actor", ActorService))
