"""From loops to a corrected trajectory: the pose graph (`pose_graph`) of odometry and
loop edges, optimized with GTSAM (the `[graph]` extra, imported only when a graph is
optimized), and what `disco correct` runs over a sequence (`correct_sequence`)."""
