fn main() {
    rlmflow_libtorch::link();
}
