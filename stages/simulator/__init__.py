"""The sensor simulator: a scene in, the chip's raw words out (thesis chapters 2-3)."""
