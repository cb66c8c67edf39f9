"""burrforce client: talks to a running burrforce server over its UDP wire protocol.

The UDP client, trajectory streaming and ``burrforce client demo`` arrive with the wire
protocol (proto/SPEC.md); until then this package only reserves the import name.
"""
