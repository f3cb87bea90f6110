//! surfstream-matcher: the matcher node of a graph, as a process.
fn main() {
    surfstream_runtime::shell::node_main("matcher", surfstream_matcher::node::build)
}
