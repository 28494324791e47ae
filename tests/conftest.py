import os
import tempfile

import jax

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

# One persistent compilation cache for the whole run, shared by the workers and by the commands
# the tests start (never the user's own ~/.cache).
os.environ.setdefault("JAXDYN_CACHE_DIR", os.path.join(tempfile.gettempdir(),
                                                       f"jaxdyn-test-cache-{os.getuid()}"))
