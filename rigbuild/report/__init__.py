"""The session report: the technician's decision page (summary and verdict first, pictures, a 3D view of the rig and
the takes, every metric folded), one HTML file that opens offline (its 3D data in ``report_files/`` beside it when
the page would be too large inline)."""
