"""The session report: one self-contained HTML file (images embedded) a capture technician reads."""
