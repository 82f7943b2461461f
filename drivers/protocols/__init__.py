"""Byte- and line-level codecs of the device protocols (../shared/protocols.md), free of I/O."""
