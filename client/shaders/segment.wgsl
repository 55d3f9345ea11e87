// Finding an element's segment (appended to the shaders that declare `segments`).

// The segment holding element `i` of the draw: the last one whose `first` is <= i (binary search).
fn find_segment(i: u32, seg_first: u32, seg_count: u32) -> u32 {
    var lo = seg_first;
    var hi = seg_first + seg_count;
    loop {
        if hi - lo <= 1u {
            break;
        }
        let mid = (lo + hi) / 2u;
        if segments[mid].first <= i {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return lo;
}
