# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Godot 4 editor plugin: registers the nodes in the "Add Node" dialog.
@tool
extends EditorPlugin


func _enter_tree() -> void:
	add_custom_type("BurrforceSession", "Node", preload("burrforce_session.gd"), null)
	add_custom_type("BurrforceBoneMesh", "Node3D", preload("burrforce_bone_mesh.gd"), null)
	add_custom_type("BurrforceDrillAudio", "AudioStreamPlayer",
		preload("burrforce_drill_audio.gd"), null)
	add_custom_type("BurrforceDemoTool", "Node3D", preload("burrforce_demo_tool.gd"), null)


func _exit_tree() -> void:
	remove_custom_type("BurrforceDemoTool")
	remove_custom_type("BurrforceDrillAudio")
	remove_custom_type("BurrforceBoneMesh")
	remove_custom_type("BurrforceSession")
