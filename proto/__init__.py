"""burrforce wire protocol: the language-neutral spec (SPEC.md), codec, frames and golden vectors.

The codec arrives with the wire-protocol work; until then this package only reserves the
import name.
"""
