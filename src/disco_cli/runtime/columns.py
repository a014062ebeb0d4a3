"""The columns of a query's result rows, in order, shared by `disco query` and `disco
serve` so that the two print the same rows (a module of its own: no numpy, so the
command line imports it for free)."""

RESULT_COLUMNS = [
    "query", "rank", "match", "match_id", "distance", "confidence", "yaw_deg", "yaw_conf"
]  # fmt: skip
# With a relative pose (`--pose`), after those; JSON lines also carry the whole `T`.
POSE_COLUMNS = ["roll_deg", "pitch_deg", "dx", "dy", "dz", "fitness", "accepted"]
