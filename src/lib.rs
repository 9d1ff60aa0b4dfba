//! nsdd: multilevel domain decomposition for nonsmooth discrete structures.
pub mod error;
pub mod capi;
pub mod bench;
pub mod coarse;
pub mod dd;
pub mod decomposition;
pub mod direct;
pub mod factor;
pub mod kernels;
pub mod generate;
pub mod model;
pub mod partition;
pub mod report;
pub mod result;
pub mod scene;
pub mod solve;
pub mod subdomain;
pub mod vtk;

pub use error::{Error, Result};
