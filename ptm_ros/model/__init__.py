"""The probabilistic model of a PTM (thesis Ch. 1–2): topologies as set partitions and their priors,
the landmark visits, the odometry, appearance and laser likelihoods, the posterior ``log P(T | Z)`` and
the PTM result type. Depends on nothing else in ptm_ros but :mod:`ptm_ros.errors`."""
