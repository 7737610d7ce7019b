"""What is checked around a solve: the consensus that leaves out bad images and corners before it, the
final check after it, the labelling of a symmetric target, and a capture that splits (a camera moved)."""
