"""``sage export-bundle``: a minimal deployment directory for the trained team.

Contents:
  trees.json         the trees, human-readable: every node's predicate with feature
                     names and its unit split vector / threshold, every leaf's
                     affine command (K, beta) and bias command, action bounds;
  sage_qp/           the exact joint CBF-QP: common/shield/qp.py and the common modules it
                     imports, copied with only those imports made package-relative;
  bundle_runtime.py  the runtime (verbatim copy of common/audit/bundle_runtime.py),
                     numpy + sage_qp only;
  README.md          how to load and call it.
"""
from __future__ import annotations

import ast
import hashlib
import json
import re
from pathlib import Path

import numpy as np

from common.audit import bundle_runtime
from common.audit.config import AuditConfig
from common.audit.params import feature_names as resolve_names
from common.audit.params import feature_units_of, split_carriers
from common.audit.tree_view import describe_tree

README = """# SAGE deployment bundle

Hard oblique tree policies (one per carrier) and the exact joint CBF-QP shield.
Requires numpy and the QP solver's own dependencies (numba for the default
dual active-set backend; osqp/scipy only if the `osqp` backend is asked for);
no torch, no Zenoh.

```python
import sys; sys.path.insert(0, "{dirname}")
from bundle_runtime import Bundle

bundle = Bundle.load("{dirname}")
a_exec, traces = bundle.act(obs, (C, c, row_mask), fixed_mask=None, human_action=None)
```

* `obs`: `[N, obs_dim]` or `[B, N, obs_dim]` observations, features in the order of
  `trees.json["feature_names"]`.
* `C [(B,) M, 3N]`, `c [(B,) M]`, `row_mask [(B,) M]`: the affine safety rows `C a >= c`.
* `fixed_mask [(B,) 3N]` bool and `human_action [(B,) 3N]`: a human-occupied slot's
  measured action, held fixed by the QP.
* returns the executed actions `[(B,) 3N]` in `[-1, 1]` (per carrier `[Δx, Δy, Δψ]`) and
  `traces` (`a_st` nominal tree command, `leaf`, `nodes`/`sides` root-to-leaf route,
  `active` QP rows, `status`, `correction_norm`).

Each internal node `k` routes right ("yes") when `w·o > b` (unit `w`); each leaf
commands `c_a + s_a ⊙ tanh(K·o + β)`. `trees.json` lists these with feature names.
Team: {n_agents} carriers, obs_dim {obs_dim}, tree depth {depth}.

The first `act` JIT-compiles the QP kernels (numba, tens of seconds); numba caches
the machine code in `sage_qp/__pycache__` when the directory is writable, so later
starts from the same directory are fast. Call `act` once at startup to warm it.
"""


_FORBIDDEN = ("torch", "zenoh", "services")


def _project_imports(source: str, path: Path) -> list[str]:
    """Dotted names ``common....`` of every ``from common.X[.Y] import ...`` in a QP
    source file; rejects anything else that would tie the bundle to the project,
    torch or Zenoh."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in ("common",) + _FORBIDDEN:
                    raise RuntimeError(f"{path}: 'import {alias.name}' cannot go into a standalone bundle")
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level or mod.split(".")[0] in _FORBIDDEN:
                raise RuntimeError(f"{path}: 'from {'.' * node.level}{mod} import' cannot go into a bundle")
            if mod.startswith("common."):
                found.append(mod)
    return found


def qp_package_sources() -> dict[str, str]:
    """The exact CBF-QP code as a self-contained package: file name -> source.

    ``common/shield/qp.py`` becomes ``__init__.py``; every ``common.*`` module it
    (transitively) imports is copied flat as ``<last name>.py`` with its
    ``from common.<...>.X import`` rewritten to ``from .X import``. Nothing else
    changes, so the bundle runs the same solver code as the training stack.
    """
    import common

    root = Path(common.__file__).parent.parent
    top = "common.shield.qp"
    sources: dict[str, str] = {}
    todo = [top]
    while todo:
        name = todo.pop()
        if name in sources:
            continue
        path = root.joinpath(*name.split(".")).with_suffix(".py")
        text = path.read_text()
        deps = _project_imports(text, path)
        for dep in set(deps):
            text = re.sub(rf"\bfrom {re.escape(dep)} import", f"from .{dep.rsplit('.', 1)[1]} import", text)
        sources[name] = text
        todo += deps
    flat = {("__init__" if n == top else n.rsplit(".", 1)[1]) + ".py": src for n, src in sources.items()}
    if len(flat) != len(sources):
        raise RuntimeError(f"QP modules {sorted(sources)} do not flatten to distinct file names")
    return flat


def _write_if_changed(path: Path, text: str) -> None:
    """Rewrite a file only when its content changes: an unchanged QP source keeps its mtime,
    which keeps numba's on-disk JIT cache in sage_qp/__pycache__ valid across re-exports."""
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


def bundle_document(params: dict, names: list[str] | None = None, cfg: AuditConfig = AuditConfig(),
                    meta: dict | None = None) -> dict:
    """The trees.json document for a flat params dict."""
    trees = split_carriers(params)
    names = resolve_names(trees[0].obs_dim, names)
    doc = {"format": bundle_runtime.FORMAT, "feature_names": names, "n_agents": len(trees),
           "act_dim": trees[0].act_dim, "action_names": ["dx", "dy", "dpsi"], "action_box": [-1.0, 1.0],
           "routing": "node k goes right ('yes') when w.o > b; children 2k+1 (no), 2k+2 (yes)",
           "leaf_command": "c_a + s_a * tanh(K o + beta)",
           "meta": meta or {}, "trees": []}
    for i, tree in enumerate(trees):
        desc = describe_tree(tree, names, cfg, units=feature_units_of(names))   # as `sage tree show` prints them
        doc["trees"].append({
            "carrier": i, "depth": tree.depth, "c_a": tree.c_a.tolist(), "s_a": tree.s_a.tolist(),
            "nodes": [{"id": n["id"], "predicate": n["predicate"], "left": n["left"], "right": n["right"],
                       "w": n["w"], "b": n["b"]} for n in desc["nodes"]],
            "leaves": [{"leaf": lf["leaf"], "id": lf["id"], "bias_command": lf["bias_command"],
                        "gains": lf["gains"], "K": lf["K"], "beta": lf["beta"]} for lf in desc["leaves"]],
        })
    return doc


def export_bundle(params: dict, out_dir: str | Path, names: list[str] | None = None,
                  meta: dict | None = None) -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = bundle_document(params, names, meta=meta)
    qp_dir = out / bundle_runtime.QP_PACKAGE
    qp_dir.mkdir(exist_ok=True)
    sources = qp_package_sources()
    for stale in qp_dir.glob("*.py"):
        if stale.name not in sources:
            stale.unlink()
    for name, src in sources.items():
        _write_if_changed(qp_dir / name, src)
    runtime = Path(bundle_runtime.__file__).read_text()
    _write_if_changed(out / bundle_runtime.RUNTIME_FILE, runtime)
    # the exported python, byte for byte: Bundle.load refuses a bundle whose files differ
    texts = {bundle_runtime.RUNTIME_FILE: runtime, **{f"{bundle_runtime.QP_PACKAGE}/{n}": src
                                                     for n, src in sources.items()}}
    doc["code_sha256"] = {rel: hashlib.sha256(text.encode()).hexdigest() for rel, text in sorted(texts.items())}
    with open(out / bundle_runtime.TREES_FILE, "w") as f:
        json.dump(doc, f, indent=1, ensure_ascii=False, allow_nan=False)
    t0 = doc["trees"][0]
    (out / "README.md").write_text(README.format(dirname=out.name, n_agents=doc["n_agents"],
                                                 obs_dim=len(doc["feature_names"]), depth=t0["depth"]))
    return out
