"""The benchmarks behind ``burrforce bench …``: what a user measures on their own machine and
hardware (one module per bench, sharing ``runner``'s flags and closing print), and the pieces
they are built from (grooves, burr shapes, a ``burrforce serve`` process, timing helpers).
Each writes its results where ``--out`` says, by default into a fresh folder (``runner``).

The project's own measurements (the container image, the live view in a browser, the emulated
Falcon, callgrind profiles) live in the checkout's ``benchmarks/`` package, not here."""
