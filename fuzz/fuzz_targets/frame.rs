//! Fuzz the frame decoder: bytes pushed in arbitrary chunks never panic, never yield a frame over the limit, and
//! the frames come out the same however the stream is split.
#![no_main]

use canopy_protocol::frame::FrameDecoder;
use libfuzzer_sys::fuzz_target;

fn frames(data: &[u8], chunk: usize) -> (Vec<Vec<u8>>, bool) {
    let mut d = FrameDecoder::new(256);
    let mut out = Vec::new();
    for part in data.chunks(chunk.max(1)) {
        d.push(part);
        loop {
            match d.next_frame() {
                Ok(Some(f)) => {
                    assert!(!f.is_empty() && f.len() <= 256);
                    out.push(f.to_vec());
                }
                Ok(None) => break,
                Err(_) => return (out, false),
            }
        }
    }
    (out, d.finish().is_ok())
}

fuzz_target!(|data: &[u8]| {
    let Some((&split, rest)) = data.split_first() else { return };
    let whole = frames(rest, rest.len());
    let pieces = frames(rest, usize::from(split % 17) + 1);
    assert_eq!(whole, pieces);
});
