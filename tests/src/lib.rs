//! Shared helpers for the golden tests.
