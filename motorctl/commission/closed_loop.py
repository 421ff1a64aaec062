"""``motorctl identify``'s closed-loop before/after: the axis's C2 on the simulated plant of a
config, once with the nominal fitted model alone (*before*) and once with the augmented model
and the found effects compensated (*after*), each a virtual-clock run of the same length.

The runs go to one worker process forked when :class:`ClosedLoop` is made, before the caller
imports the identification and fits: the worker loads the loop (its modules and compiled
kernels) meanwhile on the other core, runs *before* as soon as the nominal fit is known
(:meth:`ClosedLoop.before`, during the effect search) and *after* once the effects are chosen
(:meth:`ClosedLoop.after`). *After* is not run ahead on the model the search has so far: the
selection's last stages (elimination, the values polished, the refit) change the values of
nearly every log, so such a run was almost always made again, and on two cores its CPU slowed
the search it waited for (``benchmarks/bench_ident.py``: 4.26 → 3.78 s wall, 6.6 → 5.8 s CPU on
the cogging log). On a single core, or where ``fork`` is not available, the runs are
made in this process when their results are asked for. Each run is deterministic: the figures
are the same either way.

This module imports the standard library only, so that the worker is forked early and cheaply.
"""

from __future__ import annotations

import copy
import gc
import multiprocessing
import os
import pickle
import traceback

#: the worker's warm-up run [s]: enough cycles to load every compiled kernel of the loop
WARM_UP_S = 0.002


def run_once(cfg: dict, name: str, axis: str, duration_s: float) -> dict:
    """One virtual-clock run of the config dict ``cfg`` (shown as ``name``): the figures of
    ``axis``, {e_M_um, e_F_um, L2_um [µm], u_peak_V [V], fault (text, '' when none)}.

    Raises:
        motorctl.inputs.InputError: ``cfg`` is not a valid config.
    """
    from motorctl.app.job import run_job
    from motorctl.config import config_from_dict
    loaded = config_from_dict(cfg, f"<identify closed loop: {name}>")
    r = run_job(loaded, duration_s=duration_s, clock="virtual").axes[axis]
    out = {k: float(r[k]) for k in ("e_M_um", "e_F_um", "L2_um", "u_peak_V")}
    out["fault"] = r["fault"]
    return out


def _serve(conn, warm: dict, axis: str) -> None:
    """The worker: a short run of ``warm`` (loads the modules and kernels), then the jobs
    received, (name, number, cfg, duration [s]), in order, each answered with (name, number,
    figures, None) or (name, number, None, the exception it raised); a job with a newer one of the same
    name waiting behind it is skipped (superseded). Ends at None or the end of the pipe."""
    try:
        run_once(warm, "warm-up", axis, WARM_UP_S)
    except Exception:      # the job itself will report what is wrong
        pass
    queue: list = []
    while True:
        try:
            if not queue:
                # idle: collect and freeze the heap now. A run's set-up collects before its
                # first cycle (motorctl.loop.rt.setup_realtime) and would otherwise traverse the
                # whole loaded loop again (0.12 s of an 8 s run's 0.45 s), and the run ends by
                # unfreezing (rt.restore)
                gc.collect()
                gc.freeze()
                queue.append(conn.recv())
            while conn.poll():
                queue.append(conn.recv())
        except EOFError:
            return
        job = queue.pop(0)
        if job is None:
            return
        name, number, cfg, duration_s = job
        if any(j is not None and j[0] == name for j in queue):
            continue
        try:
            conn.send((name, number, run_once(cfg, name, axis, duration_s), None))
        except Exception as exc:
            try:
                pickle.loads(pickle.dumps(exc))
            except Exception:              # an exception that does not cross: its text
                exc = RuntimeError("".join(traceback.format_exception_only(type(exc), exc)).strip())
            conn.send((name, number, None, exc))


class ClosedLoop:
    """The before/after runs of one axis (see the module docstring).

    Args:
        cfg: a config dict whose simulated plant carries the effect (e.g. a run log's header);
            not modified. axis: the axis to run (a key of ``cfg['axes']``). duration_s: length
            of each run [s].
    """

    def __init__(self, cfg: dict, axis: str, duration_s: float):
        base = copy.deepcopy(cfg)
        base["axes"] = {axis: base["axes"][axis]}
        base["loop"]["clock"] = "virtual"
        base["loop"].setdefault("realtime", {})["policy"] = "off"
        ctl = base["axes"][axis]["controller"]
        ctl.pop("compensation", None)
        ctl["type"] = "c2"
        self.base, self.axis, self.duration_s = base, axis, float(duration_s)
        self._before_theta = None
        self._jobs: dict = {}        # name -> (number, config) of the last one sent
        self._number = 0
        self._results: dict = {}     # name -> (figures, the exception raised or None)
        self._conn = self._proc = None
        if (os.cpu_count() or 1) >= 2 and "fork" in multiprocessing.get_all_start_methods():
            ctx = multiprocessing.get_context("fork")
            self._conn, child = ctx.Pipe()
            self._proc = ctx.Process(target=_serve, args=(child, base, axis), daemon=True,
                                     name="motorctl-closed-loop")
            self._proc.start()
            child.close()

    def _submit(self, name: str, cfg: dict) -> None:
        self._number += 1
        self._jobs[name] = (self._number, cfg)
        self._results.pop(name, None)
        if self._conn is not None:
            self._conn.send((name, self._number, cfg, self.duration_s))

    def before(self, theta) -> None:
        """Start the *before* run: C2 from the nominal fitted θ (4 or 6 values); called again
        when the nominal fit changes (the last call counts)."""
        from motorctl.ident.pipeline import set_theta0
        self._before_theta = [float(v) for v in theta]
        cfg = copy.deepcopy(self.base)
        set_theta0(cfg["axes"][self.axis]["controller"], self._before_theta)
        self._submit("before", cfg)

    def _after_config(self, idf) -> dict | None:
        """The *after* run's config for the identifier's final model and effects, or None when
        no effect has a compensation term."""
        from motorctl.ident.pipeline import compensation_from_fit, set_theta0
        comp, theta_aug, _skipped = compensation_from_fit(idf)
        if not comp:
            return None
        cfg = copy.deepcopy(self.base)
        ctl = cfg["axes"][self.axis]["controller"]
        ctl["compensation"] = comp
        set_theta0(ctl, theta_aug)
        return cfg

    def after(self, idf) -> bool:
        """Start the *after* run of an identifier after its run (a
        :class:`motorctl.ident.select.Identifier`): C2 from the augmented θ with the found
        effects compensated, and *before* again if its θ is not the identifier's final nominal
        fit. Returns False (and runs nothing) when no found effect has a compensation term."""
        cfg = self._after_config(idf)
        if cfg is None:
            self._jobs.pop("after", None)
            return False
        nominal = [float(v) for v in idf.nominal.fit.coef[:idf.n_theta]]
        if nominal != self._before_theta:
            self.before(nominal)
        if "after" not in self._jobs or self._jobs["after"][1] != cfg:
            self._submit("after", cfg)
        return True

    def _collect(self) -> None:
        while any(n not in self._results for n in self._jobs):
            if self._conn is None:
                for n, (_, cfg) in self._jobs.items():
                    if n not in self._results:
                        self._results[n] = (run_once(cfg, n, self.axis, self.duration_s), None)
                return
            try:
                name, number, figures, err = self._conn.recv()
            except EOFError:
                self._proc.join(timeout=5.0)
                raise RuntimeError("the closed-loop worker stopped without an answer "
                                   f"(exit code {self._proc.exitcode})") from None
            if number == self._jobs[name][0]:     # not a run superseded by a newer nominal fit
                self._results[name] = (figures, err)

    def result(self) -> dict | None:
        """Wait for the runs and return {"before": figures, "after": figures, "compensation":
        the entries, "controller": "c2", "duration_s"}, figures as :func:`run_once` gives them;
        None when :meth:`after` found no compensation term (or was not called).

        Raises:
            What a run raised (e.g. :class:`motorctl.inputs.InputError` for a config that is
            not valid); RuntimeError when the worker died.
        """
        if "after" not in self._jobs:
            self.close()
            return None
        try:
            self._collect()
        finally:
            self.close()
        out = {}
        for name in ("before", "after"):
            figures, err = self._results[name]
            if err is not None:
                raise err
            out[name] = figures
        comp = self._jobs["after"][1]["axes"][self.axis]["controller"]["compensation"]
        out.update(compensation=comp, controller="c2", duration_s=self.duration_s)
        return out

    def close(self) -> None:
        """Stop the worker (idempotent)."""
        if self._conn is not None:
            try:
                self._conn.send(None)
            except (BrokenPipeError, OSError):
                pass
            self._conn.close()
            self._conn = None
        if self._proc is not None:
            if any(n not in self._results for n in self._jobs):
                self._proc.terminate()       # a run nobody waits for any more
            self._proc.join(timeout=5.0)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join()
            self._proc = None


__all__ = ["ClosedLoop", "run_once"]
