"""``mirror-fg live``: the session (session.py), its frame sources, the page and its server, the saved
capture, arm joint states and the live verification."""
