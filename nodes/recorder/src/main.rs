//! surfstream-recorder: the recorder node of a graph, as a process.
fn main() {
    surfstream_runtime::shell::node_main("recorder", surfstream_recorder::node::build)
}
