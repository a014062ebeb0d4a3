"""Inputs and outputs on disk: scan readers (`readers/`), pose files (`poses/`), the
commands' scan inputs (`scan_inputs.py`), output paths, loop exports and pictures.

Kept empty so that importing one reader does not import the others.
"""
