//! PI GCS 2.0 stage protocol subset (sans-IO).
