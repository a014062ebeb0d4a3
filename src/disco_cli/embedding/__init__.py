"""The embedding stage: scans in, signatures out.

`load.py` reads scans (files or arrays) and voxelizes them into polar BEVs (with the
map's side views where asked), on a pool of threads, in input order; `batches.py`
runs the network on them one batch at a time, overlapped with that reading.

It sits above `model/` (the voxelizer and the networks) and `io/` (the scan readers)
and below `maps/` and `query/`, which hand it their scans; it never imports those.

Kept empty so that importing one module does not import the other.
"""
