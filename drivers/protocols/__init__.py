"""Byte- and line-level codecs of the device protocols (docs/protocols.md), free of I/O."""
