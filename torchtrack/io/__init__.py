"""Reading frames, videos, sequences and crops; writing results atomically."""
