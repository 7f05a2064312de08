//! The unattended service: job spool, supervisor, signals, systemd notification.
