"""The process around the library: CPU threads (`threads`, OpenBLAS's in
`blas_threads`) and the terminal (`console`, `table_layout`, the result `columns`).
"""
