"""Vibration actuators: render the burr's vibration cue (REPLY vibration_amplitude N and
vibration_frequency_hz, proto/SPEC.md §7.4) on a voice coil.

The server sends parameters; an actuator synthesizes the waveform locally (``synth``) and
silences itself when the parameter stream stops (its own watchdog). Back-ends: ``audio``
(PortAudio line out → amplifier → voice coil), ``usb_board`` (the burrforce vibration board,
``board_protocol``), ``wav`` (a file, for tests and offline review).
"""
