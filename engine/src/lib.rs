//! SCDP inference engine: `no_std`, no allocator, every buffer in one caller-provided arena.
//!
//! The data flow, one module each: [`frame`] -> [`pyramid`] -> [`anchors`] -> [`context`]
//! -> [`denoiser`] -> [`scheduler`], driven by [`policy`]. Heavy arithmetic lives in
//! [`kernels`]; [`format`] and [`weights`] read the weights file in place; [`plan`] lays out
//! the arena at compile time.
//!
//! ```no_run
//! use scdp_engine::{Aligned, Arena, ArenaPlan, Camera, Model, ModelConfig, Noise, Policy};
//!
//! const CONFIG: ModelConfig = ModelConfig::METAWORLD;
//! const PLAN: ArenaPlan = ArenaPlan::new(&CONFIG);
//! static WEIGHTS: &Aligned<[u8]> = &Aligned(*include_bytes!("../../README.md"));
//!
//! fn control_step(arena: &mut Arena<{ PLAN.arena_bytes }>, image: &[u8], state: &[f32])
//!     -> Result<(), scdp_engine::Error> {
//!     let model = Model::from_bytes(&WEIGHTS.0)?;
//!     model.expect_config(&CONFIG)?;
//!     let mut policy = Policy::new(&model, &mut arena.0)?;
//!     let k = [[100.0, 0.0, 63.5], [0.0, 100.0, 63.5], [0.0, 0.0, 1.0]];
//!     let t = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 0.0, 1.0]];
//!     policy.set_camera(Camera::new(&k, &t)?);
//!     policy.push_observation(image, state)?;
//!     let actions = policy.infer(Noise::Seed(7))?;
//!     let _chunk: &[f32] = actions.action(); // [n_action_steps, action_dim]
//!     Ok(())
//! }
//! ```
#![no_std]
#![forbid(unsafe_op_in_unsafe_fn)]

#[cfg(feature = "std")]
extern crate std;

pub mod anchors;
pub mod config;
pub mod context;
pub mod denoiser;
pub mod error;
pub mod format;
pub mod frame;
pub mod kernels;
pub mod layer;
pub mod plan;
pub mod policy;
pub mod pyramid;
pub mod rng;
pub mod scheduler;
pub mod shape;
pub mod weights;

pub use anchors::Camera;
pub use config::{BackboneNorm, ModelConfig};
pub use error::{ConfigError, Error};
pub use kernels::Backend;
pub use plan::{Aligned, Arena, ArenaPlan};
pub use policy::{Actions, Model, NoObserver, Noise, Observer, Policy, Prefix};
pub use scheduler::PrefixMode;
