//! Fixtures of published radar datasets, written in each dataset's exact layout (file names,
//! array shapes and dtypes, annotation syntax and units) with every object drawn as a return over
//! its footprint in the sensor's own geometry as its devkit documents it: what the import tests
//! and the text benchmark read. Nothing is downloaded.

pub mod datasets;
