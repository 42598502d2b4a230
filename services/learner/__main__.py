"""python -m services.learner --config RUN.json"""
import sys

from services.base import run_entry
from services.learner.service import LearnerService

if __name__ == "__main__":
    sys.exit(run_entry("learner", LearnerService))
