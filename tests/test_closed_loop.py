"""identify's closed-loop before/after (motorctl.commission.closed_loop): the worker forked ahead of
the fit gives the figures of the same runs made in this process, the last nominal fit counts,
and a fit without a compensable effect runs nothing."""

from __future__ import annotations

import pytest

import motorctl.commission.closed_loop as closed_loop
from motorctl.commission.closed_loop import ClosedLoop
from motorctl.commission.tune import make_log
from motorctl.ident.data import load_record
from motorctl.ident.select import Identifier
from motorctl.ident.synth import EXAMPLES
from motorctl.recorder.runlog import read_log

DURATION_S = 0.5


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    path = tmp_path_factory.mktemp("cl") / "cogging.mclog"
    make_log(path, EXAMPLES["cogging"], duration_s=4.0, seed=3)
    idf = Identifier(load_record(str(path), None, None, None)).run()
    assert [t.family for t in idf.terms] == ["cogging"]
    return read_log(str(path)).header["config"], idf


def _in_process(monkeypatch, cfg, idf) -> dict:
    with monkeypatch.context() as m:
        m.setattr(closed_loop.os, "cpu_count", lambda: 1)      # no worker: runs made here
        cl = ClosedLoop(cfg, "X", DURATION_S)
        assert cl._proc is None
        cl.before(idf.nominal.fit.coef[:idf.n_theta])
        assert cl.after(idf)
        return cl.result()


def test_the_worker_gives_the_figures_of_the_runs_made_here(fitted, monkeypatch):
    cfg, idf = fitted
    cl = ClosedLoop(cfg, "X", DURATION_S)
    assert cl._proc is not None and cl._proc.is_alive()
    cl.before(idf.nominal.fit.coef[:idf.n_theta])
    assert cl.after(idf)
    got = cl.result()
    assert cl._proc is None                         # the worker is gone once the result is in
    want = _in_process(monkeypatch, cfg, idf)
    assert got == want
    assert "cogging" in got["compensation"] and got["duration_s"] == DURATION_S
    assert got["after"]["fault"] == "" and got["before"]["fault"] == ""


def test_the_last_nominal_fit_counts(fitted, monkeypatch):
    cfg, idf = fitted
    cl = ClosedLoop(cfg, "X", DURATION_S)
    theta = [float(v) for v in idf.nominal.fit.coef[:idf.n_theta]]
    cl.before([2.0 * theta[0]] + theta[1:])         # a nominal fit later redone
    assert cl.after(idf)                            # the final nominal differs: before again
    got = cl.result()
    assert got == _in_process(monkeypatch, cfg, idf)


def test_no_compensable_effect_runs_nothing(fitted):
    cfg, idf = fitted
    cl = ClosedLoop(cfg, "X", DURATION_S)
    cl.before(idf.nominal.fit.coef[:idf.n_theta])
    terms, idf.terms = idf.terms, []
    try:
        assert not cl.after(idf)
    finally:
        idf.terms = terms
    assert cl.result() is None
    assert cl._proc is None


def test_a_config_that_does_not_run_gives_its_error_not_a_traceback(fitted, tmp_path):
    """identify --config with a key no config has: the worker's run fails and the CLI says
    which key, exit code 2 (the error crosses from the worker as itself)."""
    import copy

    import yaml

    from motorctl.cli import main
    from motorctl.config import ConfigError
    cfg, idf = fitted
    bad = copy.deepcopy(cfg)
    bad["loop"]["warp_factor"] = 9
    cl = ClosedLoop(bad, "X", DURATION_S)
    cl.before(idf.nominal.fit.coef[:idf.n_theta])
    assert cl.after(idf)
    with pytest.raises(ConfigError, match="warp_factor"):
        cl.result()
    assert cl._proc is None
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(bad))
    log = tmp_path / "log.mclog"
    make_log(log, EXAMPLES["cogging"], duration_s=4.0, seed=3)
    assert main(["identify", str(log), "--config", str(path), "--closed-loop-duration", "0.5"]) == 2
