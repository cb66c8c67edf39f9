# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Godot 4 only. The drill's sound from the REPLY's vibration (SPEC 7.4): a sine at the
# vibration frequency (60 000 rpm: 1 kHz), loudness from the amplitude, written into an
# AudioStreamGenerator each frame. It fades out (never clicks off) when the stream goes stale
# or a REPLY is an error, since the session then reports no vibration.
extends AudioStreamPlayer

@export var session_node: Node
## Amplitude (N) that plays at full volume.
@export var full_scale_n := 2.0
@export var mix_rate := 44100.0
## Time constant of the loudness and pitch smoothing, s.
@export var smoothing_s := 0.03

var _phase := 0.0
var _gain := 0.0
var _freq := 0.0
var _playback: AudioStreamGeneratorPlayback


func _ready() -> void:
	var gen := AudioStreamGenerator.new()
	gen.mix_rate = mix_rate
	gen.buffer_length = 0.1
	stream = gen
	play()
	_playback = get_stream_playback()


func _process(_delta: float) -> void:
	if _playback == null or session_node == null:
		return
	var s: Dictionary = session_node.last
	var target_gain := 0.0
	var target_freq := _freq
	if s.get("fresh", false):
		target_gain = clampf(s["vibration_amplitude"] / full_scale_n, 0.0, 1.0)
		if s["vibration_frequency_hz"] > 0.0:
			target_freq = s["vibration_frequency_hz"]
	var k := 1.0 - exp(-1.0 / (smoothing_s * mix_rate))
	var frames := _playback.get_frames_available()
	for i in frames:
		_gain += (target_gain - _gain) * k
		_freq += (target_freq - _freq) * k
		_phase = fmod(_phase + TAU * _freq / mix_rate, TAU)
		var v := sin(_phase) * _gain
		_playback.push_frame(Vector2(v, v))
