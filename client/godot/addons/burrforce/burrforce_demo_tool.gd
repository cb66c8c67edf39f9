# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Godot 4 only. A stand-in for a hand or a haptic device: moves this Node3D (the burr) along
# a groove so that pressing play cuts bone with no device attached. Point a
# BurrforceSession's tool_node at it. Godot frame: the bone's top surface is y = 0; the
# groove runs along -Z (the server's +x), the tool tilted back against the feed.
extends Node3D

## Where the cut starts, on the surface (m, world).
@export var start := Vector3(0.0, 0.0, -0.003)
## Depth of the cut below the surface (m): the burr centre (radius 2 mm) runs at
## 2 mm - depth_m above it.
@export var depth_m := 0.0005
@export var plunge_speed_m_s := 0.001
@export var feed_speed_m_s := 0.005
@export var feed_length_m := 0.006
## Tilt of the tool axis back against the feed (degrees from vertical).
@export var tilt_deg := 30.0

var _t := 0.0


func _ready() -> void:
	# Local +Y (the tool axis, toward the handle) leaned toward +Z, away from the feed.
	rotation_degrees = Vector3(tilt_deg, 0.0, 0.0)
	global_position = start + Vector3(0.0, 0.0025, 0.0)


func _physics_process(delta: float) -> void:
	_t += delta
	var hover := 0.0025  # start 2.5 mm up: the burr (radius 2 mm) clears the surface
	var plunge_s := (hover - (2.0e-3 - depth_m)) / plunge_speed_m_s
	var p := start
	if _t < plunge_s:
		p.y = hover - plunge_speed_m_s * _t
	else:
		p.y = 2.0e-3 - depth_m
		p.z -= minf(feed_speed_m_s * (_t - plunge_s), feed_length_m)
	global_position = p
