"""On-vehicle mapping (paper section III-A) as a stream process.

pose_graph (gtsam ISAM2, the only gtsam import) <- estimator (wheel + gyro odometry, RTK GNSS,
online scale / gyro-bias calibration, settling) <- mapper (segment -> IPM -> wait for the settled
pose -> voting grid -> sealed GridPatches) -> outbox (durable until acked) -> node (`roadmap
vehicle`: replay a drive log, upload to the owner shards) -> outputs (summary.json, poses.npz,
trajectory.tum, local_map.npz). Their accuracy against truth: services/eval/mapping.py."""
