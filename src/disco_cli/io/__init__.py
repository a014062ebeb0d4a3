"""Inputs and outputs on disk: scan readers (`readers/`), pose files (`poses/`), the
scans-in signatures-out pipeline, output paths, loop exports and pictures.

Kept empty so that importing one reader does not import the others.
"""
