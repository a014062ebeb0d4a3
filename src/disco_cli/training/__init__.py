"""Training DiSCO: data and pair mining (`data`), losses (`losses`), the loop (`loop`)."""
