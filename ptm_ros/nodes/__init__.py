"""The ROS 2 nodes of ptm_ros (rclpy): ``landmark_detector``, ``topology_filter``, ``map_publisher``, and
the ``ptm-bag-player``; :mod:`ptm_ros.nodes.common` holds what they share.

Like the command-line tools, the nodes solve many small dense systems, where multi-threaded BLAS only
thrashes; they default to one BLAS thread unless the user says otherwise (before numpy is imported).
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
