//! surfstream-replay: the tile source of a graph, as a process.
fn main() {
    surfstream_runtime::shell::node_main("replay", surfstream_replay::node::build)
}
