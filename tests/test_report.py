"""Table I aggregation against hand-computed values on synthetic results."""
import json

import pytest

from sage.report import EVAL_KEYS, load_results, summarize, table_markdown, write_report


def _result(tmp_path, method, scenario, seed, sr, col, curve_scale=1.0):
    ev = {k: 0.5 for k in EVAL_KEYS}
    ev.update(success_rate=sr, col_per_1k=col)
    data = {
        "method": method, "scenario": scenario, "seed": seed, "eval": ev, "budget": {"updates": 2},
        "train_curve": [{"progress": p, "episode_return": curve_scale * p, "drop_rate": 0.1,
                         "proposal_violation": 0.2, "correction": 0.1, "w_gap": 1.0, "cos_ind_team": 0.9,
                         **({"deploy_sr": sr} if p > 0 else {})}   # the learner's probe: not every update
                        for p in (0.0, 0.5, 1.0)],
    }
    path = tmp_path / f"{method}__{scenario}__{seed}.json"
    path.write_text(json.dumps(data))
    return path


def test_family_and_overall_means(tmp_path):
    paths = [
        _result(tmp_path, "happo", "narrow_gate", 0, 0.6, 100.0),
        _result(tmp_path, "happo", "narrow_gate", 1, 0.8, 200.0),
        _result(tmp_path, "happo", "needle_gate", 0, 0.4, 50.0),
        _result(tmp_path, "sage", "narrow_gate", 0, 0.9, 1.0),
        _result(tmp_path, "sage", "needle_gate", 0, 0.7, 0.0),
    ]
    s = summarize(load_results(paths))
    assert s["scenarios"]["narrow_gate"]["happo"]["success_rate"] == pytest.approx(0.7)
    # family mean is the mean of scenario means: (0.7 + 0.4) / 2
    assert s["families"]["LCP"]["happo"]["success_rate"] == pytest.approx(0.55)
    # overall is across runs: mean(0.6, 0.8, 0.4), population std
    assert s["overall"]["happo"]["success_rate"]["mean"] == pytest.approx(0.6)
    assert s["overall"]["happo"]["success_rate"]["std"] == pytest.approx(0.163299, abs=1e-5)
    md = table_markdown(s)
    # [95% bootstrap CI]: of the 27 equally likely resamples of (0.6, 0.8, 0.4) one has mean 0.4
    # and one 0.8 (each 3.7% > 2.5%), so the percentile interval is [40, 80]
    assert "| HAPPO | 3 | 60.0 ± 16.3 [40.0, 80.0] |" in md
    assert "N/A" in md.split("HAPPO | 3")[1].splitlines()[0]  # unshielded: no proposal-violation probe
    assert "SAGE+CBF" in md and "LCP mean" in md


@pytest.mark.sweep
def test_write_report_produces_table_and_figures(tmp_path):
    paths = [_result(tmp_path, m, "maze", 0, 0.5, 1.0) for m in ("happo", "happo_cbf", "sage")]
    out = write_report(paths, tmp_path / "report")
    assert out["runs"] == 3
    for fig in out["figures"]:
        assert (tmp_path / "report" / fig.split("/")[-1]).stat().st_size > 1000


def test_malformed_result_names_file(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"method": "happo"}))
    with pytest.raises(ValueError, match="bad.json"):
        load_results([bad])


def test_training_exposure_pools_episodes_over_updates():
    from sage.report import Result, training_exposure

    curve = [{"env_steps": 1000, "episodes": 4, "ep_collision_steps_mean": 2.0, "ep_drop_mean": 0.5},
             {"env_steps": 2000, "episodes": 6, "ep_collision_steps_mean": 0.0, "ep_drop_mean": 0.0}]
    r = Result("happo", "maze", 0, {}, curve, {})
    e = training_exposure(r)
    assert e["train_col_per_1k"] == pytest.approx(1000 * 8 / 2000)
    assert e["train_drop_rate"] == pytest.approx(2 / 10)


def test_headline_comparisons_are_computed_from_the_overall_rows(tmp_path):
    """Shield reduction HAPPO -> HAPPO+CBF, SAIL's violation reduction HAPPO+CBF -> SAIL+CBF,
    TALO's W_gap reduction SAIL+CBF -> SAGE+CBF: hand-computed on synthetic results."""
    def res(method, col, viol, w_gap, train_col):
        ev = {k: 0.5 for k in EVAL_KEYS}
        ev.update(col_per_1k=col, proposal_violation=viol)
        curve = [{"progress": p, "w_gap": w_gap, "cos_ind_team": 0.9, "env_steps": 1000 * (i + 1),
                  "episodes": 1, "ep_collision_steps_mean": train_col, "ep_drop_mean": 0.0}
                 for i, p in enumerate((0.0, 1.0))]
        path = tmp_path / f"{method}.json"
        path.write_text(json.dumps({"method": method, "scenario": "maze", "seed": 0, "eval": ev,
                                    "budget": {}, "train_curve": curve}))
        return path

    paths = [res("happo", 40.0, 0.5, 1.0, 10.0), res("happo_cbf", 1.0, 0.8, 1.0, 0.0),
             res("sail_cbf", 1.0, 0.4, 2.0, 0.0), res("sage", 0.0, 0.4, 0.5, 0.0)]
    s = summarize(load_results(paths))
    h = s["headline"]
    assert h["shield"]["col_per_1k"]["reduction_pct"] == pytest.approx(97.5)
    # training exposure: 2 collision steps over 2000 env steps = 1.0 per 1k -> 0
    assert h["shield"]["train_col_per_1k"]["from"] == pytest.approx(10.0)
    assert h["shield"]["train_col_per_1k"]["reduction_pct"] == pytest.approx(100.0)
    assert h["sail"]["proposal_violation"]["reduction_pct"] == pytest.approx(50.0)
    assert h["talo"]["w_gap"]["reduction_pct"] == pytest.approx(75.0)
    md = table_markdown(s)
    assert "97.5% lower" in md and "75.0% lower" in md
    # a zero reference gives no percentage rather than a division by zero
    paths[0] = res("happo", 0.0, 0.5, 1.0, 10.0)
    assert summarize(load_results(paths))["headline"]["shield"]["col_per_1k"]["reduction_pct"] is None


def _figures(monkeypatch, paths, out):
    """write_report's figures, kept open: {file name: matplotlib Figure}."""
    import matplotlib.pyplot as plt

    figs = {}
    real_close = plt.close
    real_savefig = plt.Figure.savefig

    def savefig(fig, path, *a, **kw):
        figs[str(path).split("/")[-1]] = fig
        return real_savefig(fig, path, *a, **kw)

    monkeypatch.setattr(plt.Figure, "savefig", savefig)
    monkeypatch.setattr(plt, "close", lambda fig=None: None)
    write_report(paths, out)
    monkeypatch.setattr(plt, "close", real_close)
    return figs


def _finite_points(ax) -> int:
    import numpy as np

    return sum(int(np.isfinite(np.asarray(line.get_ydata(), dtype=float)).sum()) for line in ax.get_lines())


def test_mechanism_note_is_a_whole_sentence(tmp_path):
    """Regression: the note ended "...with a barrier of the."."""
    path = _result(tmp_path, "sage", "maze", 0, 0.5, 1.0)
    data = json.loads(path.read_text())
    for p in data["train_curve"]:
        p.update(w_gap_first=0.5, proposal_violation_rate=0.1)
    path.write_text(json.dumps(data))
    md = table_markdown(summarize(load_results([path])))
    note = md.split("### Mechanism diagnostics")[1].split("\n\n")[1]
    assert "barrier of the." not in note
    assert note.endswith("with a barrier of the shield's own specification (a carrier disc or payload point "
                         "within its safety margin of a wall) below 0."), note


@pytest.mark.sweep
def test_deployment_probe_panel_shows_runs_too_short_for_a_curve(tmp_path, monkeypatch):
    """Regression: with one probe per run the panel was an empty plot; runs with
    several probes still draw their mean curve."""
    short = []
    for m, sr in (("happo", 0.25), ("sage", 0.75)):
        path = _result(tmp_path, m, "maze", 0, sr, 1.0)
        data = json.loads(path.read_text())
        for p in data["train_curve"]:
            if p["progress"] < 1.0:
                p.pop("deploy_sr", None)   # one probe, at the end
        path.write_text(json.dumps(data))
        short.append(path)
    figs = _figures(monkeypatch, short, tmp_path / "short")
    probe = figs["reward_drop.png"].axes[2]
    assert "deployment SR" in probe.get_title() and probe.get_ylabel()
    assert _finite_points(probe) == 2          # one point per method
    (tmp_path / "l").mkdir()
    longer = [_result(tmp_path / "l", m, "maze", 0, 0.5, 1.0) for m in ("happo", "sage")]
    probe = _figures(monkeypatch, longer, tmp_path / "long")["reward_drop.png"].axes[2]
    assert _finite_points(probe) >= 2 * 41     # each method's mean curve on the progress grid


@pytest.mark.sweep
def test_payload_panels_have_units_and_a_legend(tmp_path, monkeypatch):
    paths = [_result(tmp_path, m, "maze", 0, 0.5, 1.0) for m in ("happo", "happo_cbf", "sage")]
    fig = _figures(monkeypatch, paths, tmp_path / "r")["payload_panels.png"]
    labels = [ax.get_ylabel() for ax in fig.axes]
    for unit, label in zip(("(deg)", "(rad)", "(m)", "(s)"), labels):
        assert label.endswith(unit), labels
    (legend,) = fig.legends
    assert [t.get_text() for t in legend.get_texts()] == ["HAPPO", "HAPPO+CBF", "SAGE+CBF"]
    for ax in fig.axes:   # the bars themselves: finite, one per method
        assert len(ax.patches) == 3


def test_scenario_render_has_axis_units_and_a_legend(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    from common.env import render

    figs = []
    monkeypatch.setattr(plt, "close", lambda fig=None: figs.append(fig))
    records = render.render(str(tmp_path / "g.png"), ["narrow_gate"])
    assert records["narrow_gate"]["success"] and (tmp_path / "g.png").stat().st_size > 1000
    (fig,) = figs
    ax = fig.axes[0]
    assert ax.get_xlabel() == "x (m)" and ax.get_ylabel() == "y (m)"
    (legend,) = fig.legends
    texts = [t.get_text() for t in legend.get_texts()]
    assert {"wall", "reference route", "carriers", "payload centre"} <= set(texts), texts
