//! `sdsem-sim` binary.

fn main() {
    println!("sdsem-sim {}", env!("CARGO_PKG_VERSION"));
}
