//! surfstream-mesher: the mesher node of a graph, as a process.
fn main() {
    surfstream_runtime::shell::node_main("mesher", surfstream_mesher::node::build)
}
