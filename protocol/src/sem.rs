//! SEM imaging link protocol (sans-IO).
