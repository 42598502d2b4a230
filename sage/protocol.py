"""An experiment protocol: a TOML file that pins every setting of a campaign
(``docs/protocol/table1.toml``): scenarios, seeds, budgets, evaluation, the
settings every arm shares and each arm's own. ``sage suite --protocol FILE``
runs it; every result records the protocol's path and SHA-256, so a table
says which protocol it rests on, and a changed protocol cannot resume into
the results of the old one (their config fingerprints differ).

Schema (unknown keys are refused, so a typo cannot silently drop a setting)::

    [protocol]
    name = "table1"
    scenarios = "all"            # or a list of scenarios / families (LCP, STR, CCN)
    seeds = [0, 1, 2, 3, 4]
    updates = 300                # budget per run, learner updates
    minutes_per_run = 120        # a wall-clock cap only (whichever first)
    envs_per_actor = 32
    eval_episodes = 100          # held-out episodes per evaluated checkpoint
    eval_checkpoints = 3         # the last three checkpoints; the run's figure is their mean
    [protocol.updates_by_scenario]   # optional per-scenario budgets
    maze = 400
    [settings]                   # `sage train --set` values every arm shares
    "algo.split_k" = 0
    [arms.happo]                 # one table per arm
    method = "happo"
    [arms.sage_sparse]
    method = "sage"
    extension = true             # not one of the paper's arms
    scenarios = ["CCN"]
    settings = { "algo.split_k" = 1 }
    [calibration]                # the method-blind scripted arm (not trained)
    command = "sage env calibrate --json"
    [pilot]                      # `sage suite --protocol FILE --pilot`: the subset that sets the budgets
    arms = ["happo", "happo_cbf"]
    scenarios = ["narrow_gate", "double_gate", "l_corridor"]
    seeds = [0, 1, 2]
    updates = 300

The pilot shares every setting of the protocol's arms; only its arms, scenarios,
seeds and budget are its own, so the budgets it sets are for the very runs the
campaign makes.
"""
from __future__ import annotations

import hashlib
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from common.env.scenarios import FAMILIES, SCENARIOS
from sage.suite import Arm, SuiteConfig

_PROTOCOL_KEYS = {"name", "description", "scenarios", "seeds", "updates", "minutes_per_run", "envs_per_actor",
                  "eval_episodes", "eval_checkpoints", "updates_by_scenario", "stopping_rule"}
_ARM_KEYS = {"method", "extension", "scenarios", "settings", "title"}


@dataclass
class Protocol:
    path: str
    sha256: str
    name: str
    suite: SuiteConfig
    extension_arms: list[str] = field(default_factory=list)
    calibration: dict = field(default_factory=dict)
    text: dict = field(default_factory=dict)


def _set_items(settings: dict, where: str) -> list[str]:
    if not isinstance(settings, dict):
        raise ValueError(f"{where} must be a table of SECTION.KEY = value")
    items = []
    for key, value in settings.items():
        if not isinstance(key, str) or "." not in key:
            raise ValueError(f"{where}: {key!r} is not SECTION.KEY (e.g. algo.split_k, train.max_lag)")
        items.append(f"{key}={json.dumps(value)}")
    return items


def _scenario_list(value, where: str) -> list[str]:
    if value == "all":
        return [s for fam in FAMILIES.values() for s in fam]
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{where} must be \"all\" or a list of scenarios/families")
    out = []
    for v in value:
        members = FAMILIES.get(v, [v])
        unknown = [m for m in members if m not in SCENARIOS]
        if unknown:
            raise ValueError(f"{where}: unknown scenario {unknown[0]!r}; choose from {', '.join(sorted(SCENARIOS))} "
                             f"or a family ({', '.join(FAMILIES)})")
        out += [m for m in members if m not in out]
    return out


def load_protocol(path: str | Path, out_dir: str | None = None, pilot: bool = False) -> Protocol:
    """The suite a protocol file describes (its ``[pilot]`` subset with ``pilot``); a
    ``ValueError`` naming the first bad entry."""
    p = Path(path)
    raw_bytes = p.read_bytes()
    try:
        doc = tomllib.loads(raw_bytes.decode())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: not a TOML protocol ({exc})") from None
    unknown = set(doc) - {"protocol", "settings", "arms", "calibration", "pilot"}
    if unknown:
        raise ValueError(f"{p}: unknown sections {sorted(unknown)}")
    head = doc.get("protocol")
    if not isinstance(head, dict):
        raise ValueError(f"{p}: needs a [protocol] table")
    bad = set(head) - _PROTOCOL_KEYS
    if bad:
        raise ValueError(f"{p}: unknown [protocol] keys {sorted(bad)}")
    for key in ("name", "seeds", "updates", "eval_episodes"):
        if key not in head:
            raise ValueError(f"{p}: [protocol] needs {key!r}")
    seeds = head["seeds"]
    if not isinstance(seeds, list) or not seeds or not all(isinstance(k, int) and k >= 0 for k in seeds):
        raise ValueError(f"{p}: seeds must be a non-empty list of integers >= 0")
    by_scenario = head.get("updates_by_scenario", {})
    if not isinstance(by_scenario, dict) or not all(isinstance(v, int) and v >= 1 for v in by_scenario.values()):
        raise ValueError(f"{p}: updates_by_scenario must map scenarios to integers >= 1")
    _scenario_list(list(by_scenario), f"{p}: updates_by_scenario")
    arms_doc = doc.get("arms")
    if not isinstance(arms_doc, dict) or not arms_doc:
        raise ValueError(f"{p}: needs at least one [arms.NAME] table")
    arms, extensions = [], []
    for name, arm in arms_doc.items():
        where = f"{p}: [arms.{name}]"
        if not isinstance(arm, dict) or "method" not in arm:
            raise ValueError(f"{where} needs a method")
        bad = set(arm) - _ARM_KEYS
        if bad:
            raise ValueError(f"{where}: unknown keys {sorted(bad)}")
        scenarios = tuple(_scenario_list(arm["scenarios"], f"{where} scenarios")) if "scenarios" in arm else ()
        arms.append(Arm(name, arm["method"], tuple(_set_items(arm.get("settings", {}), f"{where} settings")),
                        scenarios))
        if arm.get("extension", False):
            extensions.append(name)
    suite = SuiteConfig(
        methods=[a.method for a in arms], arms=arms,
        scenarios=_scenario_list(head.get("scenarios", "all"), f"{p}: scenarios"), seeds=list(seeds),
        minutes_per_run=float(head.get("minutes_per_run", 600.0)), updates_per_run=int(head["updates"]),
        updates_by_scenario=dict(by_scenario), eval_episodes=int(head["eval_episodes"]),
        eval_checkpoints=int(head.get("eval_checkpoints", 1)), envs_per_actor=int(head.get("envs_per_actor", 32)),
        train_overrides=_set_items(doc.get("settings", {}), f"{p}: [settings]"),
        out_dir=out_dir or f"results/{head['name']}", protocol=str(p),
        protocol_sha256=hashlib.sha256(raw_bytes).hexdigest(),
    )
    if pilot:
        _restrict_to_pilot(suite, doc.get("pilot"), p, out_dir)
    return Protocol(path=str(p), sha256=suite.protocol_sha256, name=str(head["name"]), suite=suite,
                    extension_arms=extensions, calibration=dict(doc.get("calibration", {})), text=doc)


def _restrict_to_pilot(suite: SuiteConfig, pilot, p: Path, out_dir: str | None) -> None:
    if not isinstance(pilot, dict):
        raise ValueError(f"{p}: needs a [pilot] table for --pilot")
    bad = set(pilot) - {"arms", "scenarios", "seeds", "updates"}
    if bad or not {"arms", "scenarios", "seeds", "updates"} <= set(pilot):
        raise ValueError(f"{p}: [pilot] takes arms, scenarios, seeds and updates"
                         + (f" (unknown {sorted(bad)})" if bad else ""))
    names = {a.name for a in suite.arms}
    unknown = [a for a in pilot["arms"] if a not in names]
    if unknown:
        raise ValueError(f"{p}: [pilot] arms {unknown} are not arms of the protocol")
    suite.arms = [a for a in suite.arms if a.name in pilot["arms"]]
    suite.methods = [a.method for a in suite.arms]
    suite.scenarios = _scenario_list(pilot["scenarios"], f"{p}: [pilot] scenarios")
    seeds = pilot["seeds"]
    if not isinstance(seeds, list) or not seeds or not all(isinstance(k, int) and k >= 0 for k in seeds):
        raise ValueError(f"{p}: [pilot] seeds must be a non-empty list of integers >= 0")
    suite.seeds = list(seeds)
    if not isinstance(pilot["updates"], int) or pilot["updates"] < 1:
        raise ValueError(f"{p}: [pilot] updates must be an integer >= 1")
    suite.updates_per_run, suite.updates_by_scenario = pilot["updates"], {}
    suite.out_dir = out_dir or suite.out_dir + "_pilot"
