//! Accuracy of the dense stage against ground truth (filled in below).
