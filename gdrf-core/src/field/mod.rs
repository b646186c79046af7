//! The radiance field: deformation/correction Φ (shape side), template T (density trunk
//! T_σ, colour branch T_c) and their composition in the generator.
pub mod deform;
pub mod generator;
pub mod template;
