"""The em_sam_mapper node: EM-SAM batch and incremental mapping of the keyframes."""
