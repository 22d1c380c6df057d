# Sourced on the GPU machine from the repository root: installs .gpu/prefix.txz (benchmarks/gpu/bundle.py) into
# /tmp/gausem-prefix once, and points Python, the ROS libraries and gsplat's kernel cache at it. gsplat builds its CUDA
# kernels on first use (about 75 s on an H100/H200) into /tmp/gausem-prefix/torch_extensions; a copy of that build
# carried as .gpu/gsplat_build.tgz is reused (its sources are back-dated so that ninja does not rebuild them).
GAUSEM_PREFIX=/tmp/gausem-prefix
if [ ! -d $GAUSEM_PREFIX/site ]; then
  mkdir -p $GAUSEM_PREFIX && tar -xJf .gpu/prefix.txz -C $GAUSEM_PREFIX || return 1
  find $GAUSEM_PREFIX/site/gsplat -exec touch -d 2020-01-01 {} +
  [ -f .gpu/gsplat_build.tgz ] && mkdir -p $GAUSEM_PREFIX/torch_extensions \
    && tar -xzf .gpu/gsplat_build.tgz -C $GAUSEM_PREFIX/torch_extensions
fi
export PYTHONPATH=$PWD:$GAUSEM_PREFIX/lib/python3.12/site-packages:$GAUSEM_PREFIX/site
export LD_LIBRARY_PATH=$GAUSEM_PREFIX/lib:$(ls -d $GAUSEM_PREFIX/site/*.libs | tr '\n' ':')${LD_LIBRARY_PATH:-}
export AMENT_PREFIX_PATH=$GAUSEM_PREFIX _ROS_WHEELS_BOOTSTRAP_COMPLETE=1 PYTHONUNBUFFERED=1
export TORCH_EXTENSIONS_DIR=$GAUSEM_PREFIX/torch_extensions TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-33}
