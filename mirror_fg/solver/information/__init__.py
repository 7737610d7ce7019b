"""The Fisher information of a set-up: Cramer-Rao bounds (crb.py) and the ranking of the next mirror
placement or arm pose (suggest.py)."""
