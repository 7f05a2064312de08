//! The specimen stage: async driver over any byte stream, and the one place that opens ports.
