"""What a reconstruction writes: atomic files, density.npz and its exports, figures, sequences."""
