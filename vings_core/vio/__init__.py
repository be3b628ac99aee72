"""Visual-inertial fusion for the front end (no ROS imports): IMU pre-integration
(:mod:`.preint`), the dense-BA visual factor moved to body poses (:mod:`.visual_factor`), the
visual-inertial alignment that gives scale, gravity and gyroscope bias (:mod:`.align`) and the
sliding-window smoother in GTSAM with marginalisation (:mod:`.smoother`).

Frames: ``w`` world, ``b`` body (= IMU), ``c`` camera; ``T_bc`` camera-to-body. IMU readings follow
REP-145: specific force in m/s^2 with gravity included (about +9.81 up at rest), angular rate in
rad/s, both in the body frame. Gravity in the world is ``g_w`` (``[0, 0, -9.81]`` once aligned).
"""
