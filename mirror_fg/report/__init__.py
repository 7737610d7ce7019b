"""What a user reads of a result: the console summary (summary.py), the one verdict (verdict.py), and the
HTML/PDF report (writer.py with its pages, figures and sections)."""
