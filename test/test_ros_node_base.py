"""The node skeleton (vings_ros/node_base.py StageNode): a minimal subclass runs its worker,
publishes diagnostics from its hook, checkpoints, and shuts down in order.

Each case runs in a child process (own rclpy context, unique ROS domain, localhost only)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]

TINY_NODE = """
import json, sys, time
from pathlib import Path
from vings_ros.node_base import Level, NodeStatus, StageNode
from vings_ros.node_config import QueuePolicy
from vings_ros.registry import NodeSpec

EVENTS = []


class TinyNode(StageNode):
    spec = NodeSpec("tiny_node", "tiny", "vings_ros.node_config:CheckpointSettings", reads=("run",))
    STATUS_NAME = "vings/tiny"
    WORKER_STOP_TIMEOUT_S = 5.0

    def setup(self):
        self.queue = self.input_queue(QueuePolicy.BACKPRESSURE, 100)
        self.done = []
        self.resumed = self.resume_file() is not None
        EVENTS.append(["setup", self.worker is None])

    def step(self):
        item = self.queue.get(timeout=0.05)
        if item == "boom":
            raise RuntimeError("boom")
        if item is not None:
            self.done.append(item)
            self.mark_changed()

    def diagnostics(self):
        return NodeStatus(Level.WARN, "tiny", {"done": len(self.done), "policy": QueuePolicy.BACKPRESSURE})

    def write_checkpoint(self, path):
        path.write_text(json.dumps(self.done))
        EVENTS.append(["checkpoint", len(self.done)])
        return f"{len(self.done)} items"

    def checkpoint_ready(self):
        return bool(self.done)

    def drain(self):
        EVENTS.append(["drain", self.worker.thread.is_alive()])

    def finish(self):
        EVENTS.append(["finish", self.worker.thread.is_alive()])

    def close(self):
        EVENTS.append(["close"])
"""

DIRECT_SCRIPT = TINY_NODE + """
import rclpy
from rclpy.executors import SingleThreadedExecutor
from msg_adapters.diagnostics import parse_diagnostic_array
ck = sys.argv[1]
rclpy.init(args=["x", "--ros-args", "-p", "ros.diagnostics_period_s:=0.1",
                 "-p", f"tiny_node.checkpoint_path:={ck}", "-p", "run.eval_novel:=3"])
node = TinyNode()
sent = []
node.pub_diag.publish = sent.append
for i in range(5):
    node.queue.put(i)
ex = SingleThreadedExecutor()
ex.add_node(node)
t0 = time.time()
while time.time() - t0 < 30 and (len(node.done) < 5 or len(sent) < 2):
    ex.spin_once(timeout_sec=0.05)
diag = parse_diagnostic_array(sent[-1])["status"]["vings/tiny"]
res = {"done": node.done, "thread": node.worker.thread.name, "diag": diag,
       "eval_novel": node.config("run").eval_novel, "settings": node.settings.checkpoint_path}
node.shutdown()
res["events"] = list(EVENTS)
res["file"] = json.loads(Path(ck).read_text())
res["checkpoints"] = node.checkpoints
# a failing step stops the worker and turns /diagnostics to error
EVENTS.clear()
ex.remove_node(node)
node.destroy_node()
node2 = TinyNode()
node2.pub_diag.publish = sent.append
res["resumed"] = node2.resumed
node2.queue.put("boom")
t0 = time.time()
while time.time() - t0 < 30 and node2.error is None:
    time.sleep(0.05)
node2.publish_diagnostics()
res["error_diag"] = parse_diagnostic_array(sent[-1])["status"]["vings/tiny"]["level"]
res["error_message"] = parse_diagnostic_array(sent[-1])["status"]["vings/tiny"]["message"]
node2.shutdown()
res["events2"] = EVENTS
ex.shutdown()
node2.destroy_node()
rclpy.shutdown()
print("RESULT " + json.dumps(res))
"""


def _env() -> dict:
    return dict(os.environ, ROS_DOMAIN_ID=str(50 + os.getpid() % 50),
                ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONPATH=str(REPO))


def test_a_minimal_stage_node_runs_reports_checkpoints_and_stops_in_order(tmp_path):
    ck = tmp_path / "tiny.json"
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(DIRECT_SCRIPT), str(ck)], env=_env(),
                       cwd=REPO, capture_output=True, text=True, timeout=180)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    assert p.returncode == 0 and lines, f"child failed (rc {p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}"
    res = json.loads(lines[-1][len("RESULT "):])
    # params -> configs: the shared section, the node's own section, a library section
    assert res["settings"] == str(ck) and res["eval_novel"] == 3
    # the worker ran the step hook; the diagnostics timer published the hook's values (+ rss_mb)
    assert res["done"] == [0, 1, 2, 3, 4] and res["thread"] == "vings-tiny_node"
    diag = res["diag"]
    assert diag["level"] == "warn" and diag["message"] == "tiny"
    assert diag["values"]["done"] == "5" and diag["values"]["policy"] == "backpressure"
    assert float(diag["values"]["rss_mb"]) > 0
    # shutdown: drain (worker alive), worker stopped, finish, final checkpoint, close
    assert res["events"] == [["setup", True], ["drain", True], ["finish", False], ["checkpoint", 5], ["close"]]
    assert res["file"] == [0, 1, 2, 3, 4] and res["checkpoints"] == 1
    # the next node resumes from it; a failing step is reported as an error, no checkpoint after it
    assert res["resumed"] is True
    assert res["error_diag"] == "error" and res["error_message"] == "failed: boom"
    assert res["events2"] == [["setup", True], ["drain", False], ["finish", False], ["close"]]


MAIN_SCRIPT = TINY_NODE + """
log = Path(sys.argv[1])


class LoggedTiny(TinyNode):
    def setup(self):
        super().setup()
        self.queue.put("x")
        log.write_text("ready\\n")

    def close(self):
        super().close()
        log.write_text(json.dumps(EVENTS))


raise SystemExit(LoggedTiny.main(["tiny_node", "--ros-args", "-p", f"tiny_node.checkpoint_path:={sys.argv[2]}"]))
"""


def test_stage_node_main_stops_cleanly_on_sigint_and_refuses_bad_parameters(tmp_path):
    log, ck = tmp_path / "events.json", tmp_path / "tiny.json"
    script = textwrap.dedent(MAIN_SCRIPT)
    p = subprocess.Popen([sys.executable, "-c", script, str(log), str(ck)], env=_env(), cwd=REPO,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t_end = time.monotonic() + 120
    while not log.exists() and time.monotonic() < t_end and p.poll() is None:
        time.sleep(0.1)
    time.sleep(0.5)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 0, err
    assert json.loads(log.read_text()) == [["setup", True], ["drain", True], ["finish", False],
                                           ["checkpoint", 1], ["close"]]
    assert json.loads(ck.read_text()) == ["x"]
    # a parameter of the node's own section that its config refuses: one line, exit 2
    bad = script.replace('f"tiny_node.checkpoint_path:={sys.argv[2]}"', '"tiny_node.checkpoint_period_s:=-1.0"')
    r = subprocess.run([sys.executable, "-c", bad, str(log), str(ck)], env=_env(), cwd=REPO,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "tiny_node: checkpoint_period_s must be >= 0" in r.stderr and "Traceback" not in r.stderr
