"""The query stage: its settings (`query_policy`), the search that ranks a map's scans
(`search`, with the query's views in `query_views`), the matches and their poses
(`localize`, `relative_pose`) and online loop closure (`loop_detector`).
"""
