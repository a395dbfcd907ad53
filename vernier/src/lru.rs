//! A small least-recently-used cache for per-size state (FFT plans, apodisation windows):
//! a handful of entries, so a vector searched linearly beats any map.

/// At most `capacity` values by key; the least recently used one is evicted first.
#[derive(Debug)]
pub(crate) struct Lru<K, V> {
    /// Entries, least recently used first.
    entries: Vec<(K, V)>,
    capacity: usize,
}

impl<K: PartialEq, V> Lru<K, V> {
    /// An empty cache of `capacity` (≥ 1) entries.
    pub(crate) fn new(capacity: usize) -> Self {
        Lru {
            entries: Vec::new(),
            capacity: capacity.max(1),
        }
    }

    /// The value of `key`, made by `make` when absent; it becomes the most recently used.
    pub(crate) fn get_or_insert_with(&mut self, key: K, make: impl FnOnce() -> V) -> &mut V {
        if let Some(pos) = self.entries.iter().position(|(k, _)| *k == key) {
            let entry = self.entries.remove(pos);
            self.entries.push(entry);
        } else {
            if self.entries.len() >= self.capacity {
                self.entries.remove(0);
            }
            self.entries.push((key, make()));
        }
        let last = self.entries.len() - 1;
        &mut self.entries[last].1
    }
}

impl<K, V> Default for Lru<K, V> {
    fn default() -> Self {
        Lru {
            entries: Vec::new(),
            capacity: 1,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evicts_the_least_recently_used() {
        let mut cache = Lru::new(2);
        let mut made = 0;
        let mut get = |cache: &mut Lru<u32, u32>, k: u32| {
            *cache.get_or_insert_with(k, || {
                made += 1;
                k * 10
            })
        };
        assert_eq!(get(&mut cache, 1), 10);
        assert_eq!(get(&mut cache, 2), 20);
        assert_eq!(get(&mut cache, 1), 10); // 2 is now the oldest
        assert_eq!(get(&mut cache, 3), 30); // evicts 2
        assert_eq!(get(&mut cache, 1), 10);
        assert_eq!(get(&mut cache, 2), 20); // made again
        assert_eq!(made, 4);
    }
}
