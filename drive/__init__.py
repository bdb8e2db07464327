"""Closed-loop evaluation: a policy drives routes in the SUMO world and is scored like the
CARLA leaderboard 1.0 (see drive/evaluate.py, drive/score.py)."""
