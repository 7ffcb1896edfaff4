"""forward: finite-element ground truth (2D plane strain / plane stress, 3D) and ultrasound RF simulation."""
