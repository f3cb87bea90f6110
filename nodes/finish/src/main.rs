//! surfstream-finish: the finish node of a graph, as a process.
fn main() {
    surfstream_runtime::shell::node_main("finish", surfstream_finish::node::build)
}
