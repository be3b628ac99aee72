"""Shared by the benchmark scripts: run named experiments so that the last stdout line is always one
JSON object of what was measured.

A failing experiment leaves ``{"error": ...}`` in its place and the others run (exit code 1); an
experiment whose result carries ``"incomplete"`` (figures it should have are null) counts as failed
too; Ctrl-C or SIGTERM records the running experiment as interrupted, prints the JSON, then the
interrupt goes on. ``out["failed"]`` lists the failed and interrupted experiments.
"""
from __future__ import annotations

import json
import signal
import sys
from typing import Any, Callable, Iterable, Optional


def _sigterm(signum, frame):  # noqa: ARG001
    raise KeyboardInterrupt("SIGTERM")


def _interrupted(err: BaseException) -> Optional[BaseException]:
    """The KeyboardInterrupt behind ``err`` (its cause or context chain), if any."""
    seen = set()
    e: Optional[BaseException] = err
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None


def _stderr(*a) -> None:
    print(*a, file=sys.stderr, flush=True)


def run_experiments(steps: Iterable[tuple[str, Callable[[], Any]]], out: dict,
                    log: Callable[..., None] = _stderr,
                    finish: Optional[Callable[[dict], None]] = None,
                    to_json: Callable[[dict], Any] = lambda d: d) -> int:
    """Run ``steps`` (name, function) in order into ``out[name]``; ``finish(out)`` runs before the
    JSON is printed (also after a failure or an interrupt). Returns the exit code (0 or 1)."""
    old = signal.signal(signal.SIGTERM, _sigterm)
    failed: list[str] = []
    name = None
    try:
        for name, fn in steps:
            try:
                r = fn()
            except Exception as err:  # noqa: BLE001 - reported in the JSON, exit code 1
                if _interrupted(err):      # Ctrl-C inside a compiled kernel comes out as SystemError
                    raise KeyboardInterrupt(str(_interrupted(err))) from err
                failed.append(name)
                out[name] = {"error": f"{type(err).__name__}: {err}"}
                log(f"{name}: FAILED: {type(err).__name__}: {err}")
                continue
            out[name] = r
            if isinstance(r, dict) and r.get("incomplete"):
                failed.append(name)
                log(f"{name}: INCOMPLETE: {r['incomplete']}")
        name = None
    except KeyboardInterrupt as e:
        if name is not None:
            failed.append(name)
            out[name] = {"error": f"interrupted ({str(e) or 'Ctrl-C'})"}
        raise
    finally:
        out["failed"] = failed
        try:
            if finish is not None:
                finish(out)
        finally:
            print(json.dumps(to_json(out), default=str), flush=True)
            signal.signal(signal.SIGTERM, old)
    return 1 if failed else 0


def run_selected(ap, args, table: dict, log: Callable[..., None] = _stderr) -> int:
    """Run the experiments of ``table`` (name -> function) that ``args.exp`` names (comma list, in
    its order; an unknown name is a usage error of ``ap``), with the configuration and the load at
    the start in the JSON."""
    import os
    names = [e for e in args.exp.split(",") if e]
    bad = [e for e in names if e not in table]
    if bad:
        ap.error(f"unknown experiment(s) {bad}; known: {', '.join(table)}")
    out = {"config": vars(args), "load_avg_1m_start": os.getloadavg()[0]}
    return run_experiments([(n, table[n]) for n in names], out, log)
