"""The pose search: its settings, the start grid (the prior's starts too), screening, scoring
and the choice, the polish on the mesh, warm re-registration, the network's poses as further
starts, the result types and the advice of an ambiguous result. Imports ``geometry`` only.
"""
