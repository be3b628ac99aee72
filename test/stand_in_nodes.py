"""Stand-in node processes for launcher tests: each logs its start and the signal that stopped it
(monotonic time first on every line) and exits 0."""
from __future__ import annotations

from pathlib import Path

STAND_IN_NODE = """
import signal, sys, time
from pathlib import Path
log = Path(sys.argv[1])
def stop(sig, frame):
    with log.open("a") as f:
        f.write(f"{time.monotonic():.6f} got {sig}\\n")
    sys.exit(0)
signal.signal(signal.SIGINT, stop)
signal.signal(signal.SIGTERM, stop)
import os
with log.open("a") as f:
    f.write(f"{time.monotonic():.6f} started {os.getpid()}\\n")
while True:
    time.sleep(0.05)
"""


def write_stand_in_nodes(folder: Path, names: tuple[str, ...]) -> list[Path]:
    """Modules ``stand_in_<name>`` in ``folder`` (put it on PYTHONPATH) that run the stand-in node
    logging to ``folder/<name>.log``; returns the log paths in the order of ``names``."""
    (folder / "stand_in.py").write_text(STAND_IN_NODE)
    for name in names:
        (folder / f"stand_in_{name}.py").write_text(
            f"import runpy, sys\nsys.argv[1:] = [{str(folder / (name + '.log'))!r}]\n"
            f"runpy.run_path({str(folder / 'stand_in.py')!r}, run_name='__main__')\n")
    return [folder / f"{n}.log" for n in names]
