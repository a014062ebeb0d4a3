"""`disco serve`: the long-running service (`serve`, its sockets in `serve_net`) and its
standard-library client (`client`, `python -m disco_cli.service.client`).

Kept empty so that the client starts without importing numpy.
"""
