//! SCDP inference engine: `no_std`, no allocator, every buffer in one caller-provided arena.
#![no_std]
#![forbid(unsafe_op_in_unsafe_fn)]

pub mod config;
pub mod error;

pub use config::{BackboneNorm, ModelConfig};
