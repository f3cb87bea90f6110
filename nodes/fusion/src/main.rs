//! surfstream-fusion: the fusion node of a graph, as a process.
fn main() {
    surfstream_runtime::shell::node_main("fusion", surfstream_fusion::node::build)
}
