//! nsdd: multilevel domain decomposition for nonsmooth discrete structures.
pub mod error;
pub mod direct;
pub mod factor;
pub mod model;
pub mod scene;

pub use error::{Error, Result};
