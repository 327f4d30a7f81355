//! The torch operators end to end through the real binaries, in one test binary: its tests share
//! one store (see `common::scratch`), so the data stages they read alike are computed once.

mod common;
mod devices;
mod numerics;
mod operators;
mod pretrain;
mod probe;
mod segment;
