//! Fuzz the edit store's decoder of stored edits and the overlay folding them: never panic; what decodes re-encodes
//! to itself; folding any decoded log over any record count either applies or refuses each edit.
#![no_main]

use canopy_edits::{Overlay, StoredEdit};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&n, rest)) = data.split_first() else { return };
    let mut overlay = Overlay::new(u16::from(n));
    for chunk in rest.split(|&b| b == 0xff) {
        if let Ok(e) = StoredEdit::decode(chunk) {
            assert_eq!(StoredEdit::decode(&e.encode()).as_ref(), Ok(&e));
            let before = overlay.clone();
            if overlay.apply(&e).is_err() {
                assert_eq!(overlay, before, "a refused edit changes nothing");
            }
        }
    }
    if overlay.version() > 0 {
        let _ = overlay.delta(0);
    }
});
