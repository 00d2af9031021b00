//! Bands of an image for image-parallel ranks: the cut of tile rows into
//! bands, and the order rank 0 hands them out in.

/// The bands of `rows` tile rows for `ranks` ranks, `per_rank` each (fewer
/// where there are fewer rows): `[start, end)`.
pub fn bands(rows: u32, ranks: usize, per_rank: u32) -> Vec<(u32, u32)> {
    let n = rows.min(per_rank.max(1) * ranks as u32).max(1);
    (0..n)
        .map(|i| (rows * i / n, rows * (i + 1) / n))
        .filter(|(a, b)| b > a)
        .collect()
}

/// The bands of one view as rank 0 hands them out: each rank owns a
/// contiguous section of the image (`ranks` sections of the bands in
/// order) and takes its own bands from the front; a rank whose section is
/// done takes the last band of the section with the most left. A rank thus
/// draws neighbouring rows, whose rays meet the same bricks (fewer bricks
/// loaded twice than with bands dealt in turn), and the balance stays
/// dynamic.
#[derive(Debug, Default, Clone)]
pub struct Sections(Vec<std::collections::VecDeque<(u32, u32)>>);

impl Sections {
    pub fn new(bands: Vec<(u32, u32)>, ranks: usize) -> Sections {
        let ranks = ranks.max(1);
        let n = bands.len();
        let mut s = vec![std::collections::VecDeque::new(); ranks];
        for (i, b) in bands.into_iter().enumerate() {
            s[i * ranks / n.max(1)].push_back(b);
        }
        Sections(s)
    }

    /// The next band for `rank`, if any is left.
    pub fn take(&mut self, rank: usize) -> Option<(u32, u32)> {
        if let Some(b) = self.0.get_mut(rank).and_then(|q| q.pop_front()) {
            return Some(b);
        }
        let most = (0..self.0.len()).max_by_key(|&r| (self.0[r].len(), std::cmp::Reverse(r)))?;
        self.0[most].pop_back()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bands cover the rows once, in order.
    #[test]
    fn bands_cover_the_rows() {
        for (rows, ranks, per) in [(34, 2, 4), (3, 4, 4), (1, 1, 1), (100, 3, 4)] {
            let b = bands(rows, ranks, per);
            assert_eq!(b.first().unwrap().0, 0);
            assert_eq!(b.last().unwrap().1, rows);
            assert!(b.windows(2).all(|w| w[0].1 == w[1].0 && w[0].0 < w[0].1));
            assert!(b.len() as u32 <= (per * ranks as u32).min(rows));
        }
    }

    /// Every band is handed out exactly once whatever order the ranks ask
    /// in; a rank first draws its own section front to back, then the
    /// back of the section with the most left.
    #[test]
    fn sections_hand_out_every_band_once() {
        let b = bands(64, 2, 4);
        let mut s = Sections::new(b.clone(), 2);
        // Rank 0's section is the first half, in order.
        assert_eq!(s.take(0), Some(b[0]));
        assert_eq!(s.take(0), Some(b[1]));
        assert_eq!(s.take(1), Some(b[4]));
        assert_eq!(s.take(0), Some(b[2]));
        assert_eq!(s.take(0), Some(b[3]));
        // Rank 0's section is done: it takes the last of rank 1's.
        assert_eq!(s.take(0), Some(b[7]));
        assert_eq!(s.take(1), Some(b[5]));
        assert_eq!(s.take(1), Some(b[6]));
        assert_eq!(s.take(0), None);
        assert_eq!(s.take(1), None);
        // Random askers: each band once.
        let mut seed = 12345u64;
        for ranks in 1..=5usize {
            let b = bands(37, ranks, 4);
            let mut s = Sections::new(b.clone(), ranks);
            let mut got = vec![];
            loop {
                seed = seed
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let r = (seed >> 33) as usize % ranks;
                match s.take(r) {
                    Some(x) => got.push(x),
                    None if (0..ranks).all(|r| s.take(r).is_none()) => break,
                    None => {}
                }
            }
            got.sort();
            assert_eq!(got, b, "{ranks} ranks");
        }
    }
}
