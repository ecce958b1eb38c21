"""EM-SAM: batch SAM with EM weights that find moveable landmarks (paper 000)."""
