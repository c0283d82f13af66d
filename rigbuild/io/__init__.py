"""File I/O at the edges of the library. Every writer is atomic: a crash never leaves a half-written file."""
