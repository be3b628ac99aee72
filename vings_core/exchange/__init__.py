"""The pose exchange: how every stage that moves keyframe poses tells the others.

Keyframe poses (``T_wc``, identified by the keyframe's image stamp) are held by several stages at
once: the front end (window BA, later the IMU smoother), the mapper (pose refinement), the loop
closer (pose graph). Each moves them, and none may overwrite another's move. So poses travel as
*increments* ``C`` (world-frame similarities, ``T_new = C ∘ T_old``, see
:func:`vings_core.geometry.sim3_apply_to_pose`) in numbered batches (:class:`IncrementBatch`).

The topology is a star around one **keeper** (the front end, whose poses are the trajectory):

* a **writer** (mapper, loop closer, any other stage) applies its own move at once and sends it to
  the keeper as a batch (its source name, its sequence number, the last keeper batch it had seen);
* the keeper applies each batch under the **write-back policy** of its source
  (:class:`WritebackPolicy`: ``none``, ``all``, or ``consistent``: a chi-square gate against its own
  visual pose information) and sends its net moves (its own and the ones it accepted) as one batch,
  with the last batch it processed of every source (the *acks*);
* every writer follows the keeper's batches (:class:`PoseFollower`): increments that crossed in
  flight are composed exactly (a move of its own that the keeper had not seen yet stays on top of
  the keeper's move; one the keeper refused is undone), so no increment is lost or applied twice.

``vings run`` passes the batches in memory; the nodes pass them on ``/vings/exchange/<source>``
(``msg_adapters.exchange``, standard ``nav_msgs/Path``; docs/ros.md).
"""
from .batch import IncrementBatch
from .config import ExchangeConfig, WritebackPolicy
from .follower import PoseFollower
from .keeper import PoseKeeper
from .owner import PoseOwner
from .policy import correction_consistency

__all__ = ["ExchangeConfig", "IncrementBatch", "PoseFollower", "PoseKeeper", "PoseOwner",
           "WritebackPolicy", "correction_consistency"]
