//! surfstream-wavelet: the wavelet node of a graph, as a process.
fn main() {
    surfstream_runtime::shell::node_main("wavelet", surfstream_wavelet::node::build)
}
